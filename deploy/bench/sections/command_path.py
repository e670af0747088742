"""Section: the command path under a flood of valid commands, with the robot as its own process."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from deploy.bench.fmt import results_of
from deploy.bench.section import Context, Results, Section, Verdict

TITLE = "The command path under a flood"

#: the issue's goals: stimuli at this share of their normal rate or better during a flood
RATE_RATIO_GOAL = 0.9
#: and the arm still within this long of the sender's last send
ARM_STOP_GOAL_MS = 400.0


@dataclass(frozen=True)
class CommandPathSizes:
    cmd_flood_messages: int  # jogs in the flood
    cmd_cost_messages: int  # messages timed through the intake


SIZES = {
    "full": CommandPathSizes(cmd_flood_messages=100000, cmd_cost_messages=20000),
    "quick": CommandPathSizes(cmd_flood_messages=30000, cmd_cost_messages=5000),
    "smallest": CommandPathSizes(cmd_flood_messages=2000, cmd_cost_messages=500),
}


def measure(ctx: Context, sizes: CommandPathSizes) -> dict[str, Any]:
    from deploy.bench.command_path import measure as flood

    return flood(sizes.cmd_flood_messages, 2.0, sizes.cmd_cost_messages)


def verdicts(results: Results) -> list[Verdict]:
    """The flood's goals, stated in the section's own text."""
    r = results_of(results, "command_path")
    if r is None:
        return []
    return [
        Verdict(
            f"stimuli at {RATE_RATIO_GOAL:g} of their normal rate or better, the arm still "
            f"within {ARM_STOP_GOAL_MS:g} ms of the last send",
            f"{r['rate_ratio']:.2f} of normal, {r['arm_moving_ms_after_last_send']:.0f} ms",
            r["rate_ratio"] >= RATE_RATIO_GOAL
            and r["arm_moving_ms_after_last_send"] <= ARM_STOP_GOAL_MS,
            table=None,
        )
    ]


def markdown(results: Results) -> list[str]:
    """The report's section on the command path."""
    r = results_of(results, "command_path")
    out = ["", f"## {TITLE}", ""]
    if r is None:
        return [*out, "Not run."]
    c, n, d = r["cost"], r["interval_ms_normal"], r["interval_ms_during"]
    counters = r["robot_counters"]
    (goal,) = verdicts(results)
    verdict = "**pass**" if goal.passed else "**fail**"
    out += [
        "The robot node runs as its own process with its real ur-rtde and Robotiq socket "
        "drivers against their simulators (`deploy/bench/command_path.py`, the rig the system "
        "tests use too). A client written from docs/protocol.md alone syncs clocks, jogs the "
        f"arm, then sends {r['flood_messages']:,} valid `arm_jog` commands as fast as one "
        f"process can ({r['flood_s']:.2f} s here). Intervals are taken from the robot's own "
        f"send stamps. Goals (issue's test): {goal.what}: {verdict}.",
        "",
        "| what | measured |",
        "|---|---|",
        f"| one command through the intake (read, decode, admission), in batches of 32 | "
        f"median {c['median_us']:.1f} us, p99 {c['p99_us']:.1f} us ({c['messages']:,} "
        "messages) |",
        f"| stimuli per second, before / during the flood and its backlog (2 s after) | "
        f"{r['stimuli_per_s_normal']:.1f} / {r['stimuli_per_s_during']:.1f} "
        f"({r['rate_ratio']:.2f} of normal) |",
        f"| interval between stimuli before the flood | median {n['median']:.1f} ms, "
        f"max {n['max']:.1f} ms |",
        f"| interval between stimuli during it | median {d['median']:.1f} ms, "
        f"p99 {d['p99']:.1f} ms, max {d['max']:.1f} ms |",
        f"| the arm (UR simulator) still moving after the sender's last send | "
        f"{r['arm_moving_ms_after_last_send']:.0f} ms |",
        f"| robot's counters (heartbeat) | {counters['commands_received']:,.0f} read, "
        f"{counters['commands_stale']:,.0f} stale, "
        f"{counters['commands_superseded']:,.0f} superseded, "
        f"{counters['commands_applied']:,.0f} applied, "
        f"{counters['command_backlog_pauses']:,.0f} backlog pauses |",
        "",
        "The robot reads at most 32 operator messages per loop turn and, after a full batch, "
        "leaves its command socket alone for 8 ms while frames go on; what waits meanwhile only "
        "ages, and a command older than 250 ms (the operator's send time) is refused. The rest "
        "of a flood waits in ZeroMQ's and the kernel's queues or is dropped by the sender's PUB "
        "at its high-water mark. On this 2-core machine the flooding process takes a core of "
        "its own, so the robot shares the other with the simulators and this bench.",
    ]
    if "date" in r:
        before, after = r["load_before"]["loadavg_1m"], r["load_after"]["loadavg_1m"]
        out += [
            "",
            f"Measured {r['date']}, machine load (1 min) {before} before and {after} after.",
        ]
    return out


SECTION = Section(
    name="command_path",
    title=TITLE,
    sizes=SIZES,
    measure=measure,
    markdown=markdown,
    verdicts=verdicts,
)
