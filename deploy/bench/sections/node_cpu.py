"""Section: the CPU both nodes take as deployed, processes linked over loopback TCP."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from deploy.bench.fmt import num, results_of, table
from deploy.bench.section import Context, Results, Section, Verdict

TITLE = "Node CPU"

#: the issue's targets, percent of one core
ROBOT_CPU_TARGET = 10.0
OPERATOR_CPU_TARGET = 5.0
#: the rate the bench's board sends scans at: the sensor's, which the targets are for
SENSOR_RATE_HZ = 120.0
#: below this share of its cap the robot rendered too few frames for its CPU to count
RENDERED_SHARE_TO_COUNT = 0.9


@dataclass(frozen=True)
class NodeCpuSizes:
    node_warmup_s: float
    node_measure_s: float


SIZES = {
    "full": NodeCpuSizes(node_warmup_s=5.0, node_measure_s=20.0),
    "quick": NodeCpuSizes(node_warmup_s=4.0, node_measure_s=6.0),
    "smallest": NodeCpuSizes(node_warmup_s=3.0, node_measure_s=2.0),
}


def measure(ctx: Context, sizes: NodeCpuSizes) -> dict[str, Any]:
    """The nodes are processes of their own: unpinned (they inherit the bench's affinity)."""
    from deploy.bench.nodecpu import run_nodes

    return run_nodes(ctx.demo_frames(), SENSOR_RATE_HZ, sizes.node_warmup_s, sizes.node_measure_s)


def _control_rate_hz() -> float:
    """The operator's servo goal rate, as its renderer is configured by default."""
    from operator_side.renderer import RendererConfig

    return RendererConfig().control_rate_hz


def verdicts(results: Results) -> list[Verdict]:
    """Each node against its target; a robot that fell behind its cap cannot pass."""
    cpu = results_of(results, "node_cpu")
    behind = False
    rendered = None
    if cpu is not None:
        rendered = cpu.get("robot_window_per_s", {}).get("frames_processed")
        behind = (
            rendered is not None and rendered < RENDERED_SHARE_TO_COUNT * cpu["publish_rate_hz"]
        )
    rows = []
    operator = f"operator node at {_control_rate_hz():g} Hz"
    for node, key, target in (
        (f"robot node at {SENSOR_RATE_HZ:g} Hz", "robot_cpu_percent", ROBOT_CPU_TARGET),
        (operator, "operator_cpu_percent", OPERATOR_CPU_TARGET),
    ):
        val = None if cpu is None else cpu.get(key)
        text = None if val is None else f"{val:.1f} %"
        verdict = None if val is None else val < target
        if val is not None and behind:
            # a robot that renders fewer frames than its cap costs less: not a valid pass
            text += (
                f" (the robot rendered only {rendered:.0f} of {cpu['publish_rate_hz']:g} "
                "frames/s: the machine was too loaded for this to count)"
            )
            verdict = False if val >= target else None
        rows.append(Verdict(f"{node}: < {target:g} % of one core", text, verdict))
    return rows


def markdown(results: Results) -> list[str]:
    s = results_of(results, "node_cpu")
    out = ["", f"## {TITLE}", ""]
    if s is None:
        return [*out, "Not run."]
    out += [
        f"Both nodes as processes (`deepxpalm robot` / `deepxpalm operator` with a config "
        f"file, as deployed: every core, no thread limits), linked over loopback TCP. The "
        f"robot's board is a pty this bench writes the demo scene's scans to at "
        f"{s['rate_hz']:g} Hz (delivered: {s['scans_per_s']:.1f}/s); the operator drives the "
        f"recording servo bus at its {_control_rate_hz():g} Hz control rate. utime + stime "
        f"from /proc over {s['measure_s']:g} s after a warm-up.",
        "",
    ]
    win = s.get("robot_window_per_s", {})
    op_wakeups = s.get("operator_stats", {}).get("wakeups")
    out += [
        f"Inside the window the robot read {num(win.get('frames_captured'))} frames/s, "
        f"rendered {num(win.get('frames_processed'))}/s (cap {s['publish_rate_hz']:g}) and "
        f"let {num(win.get('frames_superseded'))}/s be superseded before its loop took them; "
        f"its loop woke {num(win.get('wakeups'))} times/s"
        + (
            ""
            if op_wakeups is None
            else f", the operator's {op_wakeups:,.0f} times over the whole run"
        )
        + ". "
        "CPU per thread (% of one core): robot "
        + ", ".join(f"{k} {v:g}" for k, v in s.get("robot_threads_percent", {}).items())
        + "; operator "
        + ", ".join(f"{k} {v:g}" for k, v in s.get("operator_threads_percent", {}).items())
        + " (main: the node's loop; the other Python thread: the serial reader; ZMQbg: "
        "ZeroMQ's I/O thread).",
        "",
    ]
    out += table(
        ["node", "CPU (% of one core)", "target", "counters over the whole run"],
        [
            [
                f"robot, {SENSOR_RATE_HZ:g} Hz frames",
                num(s.get("robot_cpu_percent")),
                f"< {ROBOT_CPU_TARGET:g} %",
                ", ".join(f"{k} {v:g}" for k, v in s.get("robot_stats", {}).items()),
            ],
            [
                f"operator, {_control_rate_hz():g} Hz control",
                num(s.get("operator_cpu_percent")),
                f"< {OPERATOR_CPU_TARGET:g} %",
                ", ".join(f"{k} {v:g}" for k, v in s.get("operator_stats", {}).items()),
            ],
        ],
        "|---|---:|---:|---|",
    )
    return out


SECTION = Section(
    name="node_cpu",
    title=TITLE,
    sizes=SIZES,
    measure=measure,
    markdown=markdown,
    verdicts=verdicts,
)
