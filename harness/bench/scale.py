"""Scale: the robot node's cost against frame rate, and sensor streams per core.

Two views that check each other:

- measured: the robot node as a process on a pty board at 120, 500 and
  1000 Hz, with the default 60 Hz render cap and with every frame
  rendered; CPU time per second of wall time from /proc;
- modelled: per-frame stage medians from the latency budget. Every frame
  is read (decode + calibration); at most ``publish_rate_hz`` of them are
  rendered (sanitize, classify, downsize, mask, encode, send). One core
  serves as many streams as fit in a second of its time.

The model leaves out the node's fixed costs (heartbeats, the event loop,
the reader thread's wake-ups), which the measurement includes: their
difference is that overhead.

As a bench section: frame rate and streams per core, modelled from stage
medians, measured on the node.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from harness.bench.fmt import IMG_DIR, num, pyplot, results_of, save_figure, table
from harness.bench.node_cpu import ROBOT_CPU_TARGET, run_nodes
from harness.bench.section import Context, Results, Section

log = logging.getLogger(__name__)

READ_STAGES = ("wire_decode", "calibration")
RENDER_STAGES = ("sanitize_contact", "classification", "render", "encode")


def modelled(
    stage_medians_us: dict[str, float],
    transit_send_us: float,
    rates: tuple[float, ...],
    cap_hz: float,
) -> list[dict[str, Any]]:
    """CPU microseconds per second of one stream, and streams per core, from stage medians."""
    read = sum(stage_medians_us.get(s, 0.0) for s in READ_STAGES)
    stages = RENDER_STAGES
    if "frame_step" in stage_medians_us:  # the node's path: one compiled call for three
        stages = ("frame_step", "encode")
    render = sum(stage_medians_us.get(s, 0.0) for s in stages) + transit_send_us
    rows = []
    for rate in rates:
        for capped in (True, False):
            rendered = min(rate, cap_hz) if capped else rate
            us_per_s = rate * read + rendered * render
            rows.append(
                {
                    "rate_hz": rate,
                    "capped": capped,
                    "rendered_per_s": rendered,
                    "cpu_percent": us_per_s / 1e4,
                    "streams_per_core": int(1e6 // us_per_s) if us_per_s > 0 else None,
                }
            )
    return rows


def measured(
    frames: list[np.ndarray],
    rates: tuple[float, ...],
    warmup_s: float,
    measure_s: float,
    cap_hz: float,
    backends: tuple[str | None, ...] = (None,),
    decompose: bool = True,
) -> list[dict[str, Any]]:
    """The robot node alone (no operator) at each rate, capped and uncapped.

    ``decompose`` adds two runs that split the node's cost: frames with no
    contact at the first rate (read, never classified) and a board sending
    2 scans per second (the node's fixed cost: heartbeats, timeouts).
    """
    runs: list[tuple[str, list[np.ndarray], float, float, str | None]] = []
    for rate in rates:
        for capped in (True, False):
            for backend in backends if (capped and rate == rates[0]) else (None,):
                runs.append(("demo scene", frames, rate, cap_hz if capped else rate, backend))
    if decompose:
        empty = [np.zeros_like(frames[0])]
        runs.append(("no contact", empty, rates[0], cap_hz, None))
        runs.append(("idle (2 scans/s)", empty, 2.0, cap_hz, None))
    rows = []
    for content, fr, rate, publish, backend in runs:
        r = run_nodes(
            fr,
            rate,
            warmup_s,
            measure_s,
            publish_rate_hz=publish,
            backend=backend,
            with_operator=False,
        )
        cpu = r["robot_cpu_percent"]
        rows.append(
            {
                "content": content,
                "rate_hz": rate,
                "publish_rate_hz": publish,
                "backend": r["backend"],
                "cpu_percent": cpu,
                "streams_per_core": int(100 // cpu) if cpu > 0 else None,
                "scans_per_s": r["scans_per_s"],
                "window_per_s": r.get("robot_window_per_s", {}),
                "threads_percent": r.get("robot_threads_percent", {}),
                "stats": r.get("robot_stats", {}),
            }
        )
        log.info("robot node, %s at %s Hz (cap %s): %.1f %% CPU", content, rate, publish, cpu)
    return rows


TITLE = "Scale: frame rate and streams per core"


@dataclass(frozen=True)
class ScaleSizes:
    scale_rates: tuple[float, ...]  # frame rates, Hz
    scale_measured: bool  # run the robot node (slow) besides the model
    scale_backends: tuple[str | None, ...]  # None: the node's default
    node_warmup_s: float
    node_measure_s: float  # each rate is measured for half of it


SIZES = {
    "full": ScaleSizes(
        scale_rates=(120.0, 500.0, 1000.0),
        scale_measured=True,
        scale_backends=(None, "onnxruntime", "numpy"),
        node_warmup_s=5.0,
        node_measure_s=20.0,
    ),
    "quick": ScaleSizes(
        scale_rates=(120.0, 500.0, 1000.0),
        scale_measured=False,
        scale_backends=(None,),
        node_warmup_s=4.0,
        node_measure_s=6.0,
    ),
    "smallest": ScaleSizes(
        scale_rates=(120.0, 500.0, 1000.0),
        scale_measured=False,
        scale_backends=(None,),
        node_warmup_s=3.0,
        node_measure_s=2.0,
    ),
}


def measure(ctx: Context, sizes: ScaleSizes) -> dict[str, Any]:
    from robot_side.node.config import RobotConfig

    cap = RobotConfig().publish_rate_hz
    # the sender's share of a one-process round trip: half, a rough split
    out: dict[str, Any] = {
        "cap_hz": cap,
        "modelled": modelled(ctx.stage_medians_us, ctx.tcp_transit_us / 2, sizes.scale_rates, cap),
    }
    if sizes.scale_measured:
        out["measured"] = measured(
            ctx.demo_frames(),
            sizes.scale_rates,
            sizes.node_warmup_s,
            sizes.node_measure_s / 2,
            cap,
            sizes.scale_backends,
        )
    return out


def markdown(results: Results) -> list[str]:
    s = results_of(results, "scale")
    out = ["", f"## {TITLE}", ""]
    if s is None:
        return [*out, "Not run."]
    if s.get("measured"):
        out += [
            "Measured: the robot node as a process (serial driver on a pty, default "
            "classifier, no operator), CPU time per second of wall time.",
            "",
        ]
        out += table(
            [
                "frames",
                "frame rate (Hz)",
                "render cap (Hz)",
                "backend",
                "scans/s delivered",
                "frames read/s",
                "frames rendered/s",
                "frames superseded/s",
                "CPU (% of one core)",
                "streams per core",
            ],
            [
                [
                    r.get("content", "demo scene"),
                    num(r["rate_hz"], 0),
                    num(r["publish_rate_hz"], 0),
                    r["backend"],
                    num(r["scans_per_s"], 0),
                    num(r["window_per_s"].get("frames_captured"), 0),
                    num(r["window_per_s"].get("frames_processed"), 0),
                    num(r["window_per_s"].get("frames_superseded"), 0),
                    num(r["cpu_percent"]),
                    num(r["streams_per_core"]),
                ]
                for r in s["measured"]
            ],
            "|---|---:|---:|---|---:|---:|---:|---:|---:|---:|",
        )
        out += [
            "",
            "The last two rows split the cost: frames with no contact are read but never "
            "classified; a board sending 2 scans/s leaves the node's fixed cost "
            "(heartbeats, timeouts, wake-ups). "
            "Rates are inside the measured window, from the robot's heartbeat counters. "
            "A frame is superseded when a newer one arrived before the node's loop took it: "
            "a node that falls behind reads less and so costs less, which the CPU column "
            "alone would hide.",
            "",
        ]
    out += [
        "Modelled from the paced stage medians: every frame is read (wire decode + "
        "calibration), "
        f"at most {s['cap_hz']:g} per second are rendered (sanitize, classify, downsize, mask, "
        "encode, half a loopback send); fixed costs (heartbeats, wake-ups) left out.",
        "",
    ]
    out += table(
        ["frame rate (Hz)", "rendered/s", "CPU (% of one core)", "streams per core"],
        [
            [
                num(r["rate_hz"], 0),
                num(r["rendered_per_s"], 0),
                num(r["cpu_percent"]),
                num(r["streams_per_core"]),
            ]
            for r in s["modelled"]
        ],
        "|---:|---:|---:|---:|",
    )
    out += ["", f"![scale]({IMG_DIR}/bench_scale.png)"]
    return out


def figure(result: dict[str, Any], path: Path) -> Path:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    measured = [
        r for r in result.get("measured", []) if r.get("content", "demo scene") == "demo scene"
    ]
    modelled = result["modelled"]
    for label, rows, style in (
        (
            "measured, 60 Hz render cap",
            [
                r
                for r in measured
                if r["publish_rate_hz"] < r["rate_hz"] and r["backend"] == "default"
            ],
            "o-",
        ),
        (
            "measured, every frame rendered",
            [r for r in measured if r["publish_rate_hz"] >= r["rate_hz"]],
            "s-",
        ),
        ("model, 60 Hz render cap", [r for r in modelled if r["capped"]], "o--"),
        ("model, every frame rendered", [r for r in modelled if not r["capped"]], "s--"),
    ):
        if not rows:
            continue
        seen: dict[float, float] = {}
        for r in rows:
            seen.setdefault(r["rate_hz"], r["cpu_percent"])
        xs = sorted(seen)
        ax.plot(xs, [seen[x] for x in xs], style, label=label)
    target = ROBOT_CPU_TARGET
    ax.axhline(target, color="grey", lw=0.8, ls=":")
    ax.annotate(
        f"{target:g} % budget at 120 Hz",
        (120, target),
        fontsize=8,
        xytext=(4, 4),
        textcoords="offset points",
    )
    ax.set_xlabel("frame rate (Hz)")
    ax.set_ylabel("robot node CPU (% of one core)")
    ax.set_title("robot node cost against frame rate")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    return save_figure(fig, path)


SECTION = Section(
    name="scale",
    title=TITLE,
    sizes=SIZES,
    measure=measure,
    markdown=markdown,
    figure=figure,
)
