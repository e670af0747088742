"""Section: the relay (deepxpalm relay): what it adds to latency, and what fan-out costs the robot.

Two measurements, both with CURVE on every hop and real processes
(deploy/bench/relay_fanout.py):

- **added latency**: one stream sent, in the same run, through the relay
  and straight to a subscriber that binds as a robot does today; the ratio
  of the two paths' percentiles;
- **robot CPU against observers**: a robot node connected out to the relay,
  with 1, 4 and 16 signed observers behind it (each with its own keys,
  subscribed to stimuli, heartbeats and frames, heartbeating at the observer
  rate). The relay fans the stream out, so the robot sends each message once.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from deploy.bench.fmt import num, results_of, table
from deploy.bench.section import Context, Results, Section, Verdict

TITLE = "Relay"

#: the issue's goal: the robot's CPU with 16 observers within this factor of its CPU with 1
CPU_RATIO_GOAL = 1.2
#: the issue's goal: a stalled subscriber moves no other subscriber's p99 by more than 10 %
ISOLATION_GOAL = 1.10


@dataclass(frozen=True)
class RelaySizes:
    latency_s: float
    latency_rate_hz: float
    observer_counts: tuple[int, ...]
    cpu_warmup_s: float
    cpu_measure_s: float
    isolation_s: float
    isolation_rate_hz: float


SIZES = {
    "full": RelaySizes(15.0, 100.0, (1, 4, 16), 3.0, 15.0, 20.0, 250.0),
    "quick": RelaySizes(6.0, 100.0, (1, 4, 16), 2.0, 5.0, 8.0, 250.0),
    "smallest": RelaySizes(1.5, 100.0, (1, 4), 0.5, 1.0, 1.5, 100.0),
}


def measure(ctx: Context, sizes: RelaySizes) -> dict[str, Any]:
    from deploy.bench.relay_fanout import run_isolation, run_latency, run_robot_cpu

    return {
        "latency": run_latency(sizes.latency_s, sizes.latency_rate_hz),
        "cpu": run_robot_cpu(sizes.observer_counts, sizes.cpu_warmup_s, sizes.cpu_measure_s),
        "isolation": run_isolation(sizes.isolation_s, sizes.isolation_rate_hz),
    }


def _cpu_ratio(s: dict[str, Any]) -> tuple[int, float] | None:
    rows = s.get("cpu", {}).get("rows", [])
    if len(rows) < 2 or rows[-1].get("robot_cpu_ratio") is None:
        return None
    return rows[-1]["observers"], rows[-1]["robot_cpu_ratio"]


def verdicts(results: Results) -> list[Verdict]:
    s = results_of(results, "relay")
    got = None if s is None else _cpu_ratio(s)
    if got is None:
        return [Verdict(f"robot CPU with many observers <= {CPU_RATIO_GOAL:g}x one", None, None)]
    n, ratio = got
    rows = [
        Verdict(
            f"relay: robot CPU with {n} observers <= {CPU_RATIO_GOAL:g}x with 1",
            f"{ratio:.2f}x",
            ratio <= CPU_RATIO_GOAL,
        )
    ]
    iso = s.get("isolation", {})
    r = iso.get("p99_ratio")
    rows.append(
        Verdict(
            f"relay: a stalled and a 64 kbit/s subscriber move others' p99 by <= "
            f"{ISOLATION_GOAL - 1:.0%}",
            None if r is None else f"{r:.2f}x",
            None if r is None else r <= ISOLATION_GOAL,
        )
    )
    return rows


def markdown(results: Results) -> list[str]:
    s = results_of(results, "relay")
    out = ["", f"## {TITLE}", ""]
    if s is None:
        return [*out, "Not run."]
    lat = s["latency"]
    out += [
        f"Added latency: the same stimulus stream ({lat['rate_hz']:g} Hz, a frame every 4th, "
        f"{lat['duration_s']:g} s) sent in one run through `deepxpalm relay` and straight to a "
        "subscriber that binds as a robot does today; CURVE on every hop; receive time minus "
        "send time on one machine's monotonic clock.",
        "",
    ]
    rows = []
    for label in ("direct", "via_relay"):
        r = lat.get(label, {})
        rows.append(
            [
                label.replace("_", " "),
                num(r.get("stimuli")),
                num(r.get("p50_us")),
                num(r.get("p99_us")),
            ]
        )
    rows.append(
        ["ratio (relay / direct)", "", num(lat.get("p50_ratio"), 2), num(lat.get("p99_ratio"), 2)]
    )
    out += table(["path", "stimuli", "p50 (us)", "p99 (us)"], rows, "|---|---:|---:|---:|")
    cpu = s["cpu"]
    out += [
        "",
        f"Robot CPU against observers: a robot node (scripted pads, 60 Hz stimuli, 15 Hz "
        f"frames) connected out to the relay; each observer a signed relay client with its "
        f"own keys, subscribed to the whole stream and heartbeating at "
        f"{cpu['observer_heartbeat_hz']:g} Hz (the observer rate). utime + stime from /proc "
        f"over {cpu['measure_s']:g} s after {cpu['warmup_s']:g} s.",
        "",
    ]
    out += table(
        ["observers", "robot CPU (%)", "ratio to 1", "relay CPU (%)", "stimuli per observer"],
        [
            [
                str(r["observers"]),
                num(r["robot_cpu_percent"]),
                num(r.get("robot_cpu_ratio"), 2),
                num(r["relay_cpu_percent"]),
                f"{r['stimuli_per_observer_min']}-{r['stimuli_per_observer_max']}",
            ]
            for r in cpu["rows"]
        ],
        "|---:|---:|---:|---:|---|",
    )
    iso = s.get("isolation")
    if not iso:
        return out
    c = iso["clients"]
    out += [
        "",
        f"Slow-subscriber isolation (libzmq issue 3280): the same stream ({iso['rate_hz']:g} Hz "
        f"stimuli and frames, {iso['duration_s']:g} s) into two relays; relay A also serves a "
        f"subscriber that never reads and one that reads at "
        f"{iso['slow_bytes_per_s'] * 8 / 1000:g} kbit/s, relay B two more that read "
        "everything (so B forwards at least as much as A). Two measured subscribers on each, "
        "read by one loop in one process in alternating order; pooled percentiles.",
        "",
    ]
    pooled = iso["pooled"]
    out += table(
        ["normal subscribers", "samples", "p50 (us)", "p99 (us)"],
        [
            [
                "beside a stalled and a slow one (A)",
                num(pooled["with_stalled"]["samples"]),
                num(pooled["with_stalled"]["p50_us"]),
                num(pooled["with_stalled"]["p99_us"]),
            ],
            [
                "beside two that read everything (B)",
                num(pooled["without"]["samples"]),
                num(pooled["without"]["p50_us"]),
                num(pooled["without"]["p99_us"]),
            ],
            ["ratio A / B", "", "", num(iso.get("p99_ratio"), 3)],
        ],
        "|---|---:|---:|---:|",
    )
    slow, stall = c.get("slow", {}), c.get("stall", {})
    out += [
        "",
        f"Of {num(iso.get('sent'))} stimuli sent, the stalled subscriber received "
        f"{num(stall.get('received'))} messages and the slow one {num(slow.get('stimuli'))} "
        f"stimuli, p50 {num((slow.get('p50_us') or 0) / 1e3, 0)} ms old: the relay drops for "
        "them instead of waiting, and a 64 kbit/s site gets a trickle of old data, which its "
        "palm's staleness rule (150 ms) lifts off rather than renders.",
    ]
    return out


SECTION = Section(
    name="relay",
    title=TITLE,
    sizes=SIZES,
    measure=measure,
    markdown=markdown,
    verdicts=verdicts,
)
