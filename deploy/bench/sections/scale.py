"""Section: frame rate and streams per core, modelled from stage medians, measured on the node."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from deploy.bench.fmt import IMG_DIR, num, pyplot, results_of, save_figure, table
from deploy.bench.section import Context, Results, Section
from deploy.bench.sections.node_cpu import ROBOT_CPU_TARGET

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
    from deploy.bench import scale
    from robot_side.config import RobotConfig

    cap = RobotConfig().publish_rate_hz
    # the sender's share of a one-process round trip: half, a rough split
    out: dict[str, Any] = {
        "cap_hz": cap,
        "modelled": scale.modelled(
            ctx.stage_medians_us, ctx.tcp_transit_us / 2, sizes.scale_rates, cap
        ),
    }
    if sizes.scale_measured:
        out["measured"] = scale.measured(
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
