"""Section: skipping work (no contact, identical frames, dead band, rate cap) against its error."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from deploy.bench.fmt import IMG_DIR, num, pyplot, results_of, save_figure, table
from deploy.bench.section import Context, Results, Section

TITLE = "Run time against error: skipping work"


@dataclass(frozen=True)
class SkippingSizes:
    skip_cycles: float  # of the demo scene's scripted grasps


SIZES = {
    "full": SkippingSizes(skip_cycles=2.0),
    "quick": SkippingSizes(skip_cycles=0.5),
    "smallest": SkippingSizes(skip_cycles=0.05),
}


def measure(ctx: Context, sizes: SkippingSizes) -> dict[str, Any]:
    """Savings counted at the paced stage medians (empty when the stages section was skipped)."""
    from deploy.bench.skipping import skipping

    return skipping(ctx.classifier, ctx.stage_medians_us, sizes.skip_cycles)


def markdown(results: Results) -> list[str]:
    s = results_of(results, "skipping")
    out = ["", f"## {TITLE}", ""]
    if s is None:
        return [*out, "Not run."]
    out += [
        f"The `{s['scene']}` scene's scripted grasps replayed for {s['duration_s']:.1f} s of "
        f"virtual time ({s['frames']:,} frames at {s['rate_hz']:g} Hz) through "
        "the node's `FramePipeline.offer` (rate cap included) with the node's clock made "
        "virtual, beside a shadow that "
        "classifies and renders every frame. CPU saved per skipped frame is the sum of the "
        "paced stage medians (what a frame costs in the field) it leaves out, counted on the "
        "plain path's stages (the compiled frame step leaves out the same work inside its "
        "one call; its early exits are not timed separately). Differences "
        "compare what the operator renders (the "
        "last stimulus sent) with what the shadow would have sent; for the no-contact skip, "
        "the node's all-zero stimulus with what classifying would have rendered.",
        "",
    ]
    out += table(
        [
            "what is skipped",
            "frames",
            "frames/s",
            "CPU saved (us/frame)",
            "CPU saved (us/s)",
            "largest difference (N)",
            "frames with other cells pressed",
            "largest servo goal difference (counts)",
        ],
        [
            [
                r["kind"].replace("_", " "),
                num(r["frames"]),
                num(r["frames_per_s"]),
                num(r["cpu_saved_us_per_frame"]),
                num(r["cpu_saved_us_per_s"], 0),
                f"{r['max_abs_diff_n']:.3f}",
                num(r["frames_with_other_cells"]),
                num(r["max_servo_counts_diff"]),
            ]
            for r in s["rows"]
        ],
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    )
    out += [
        "",
        f"Stimuli sent: {s['stimuli_sent']:,} plus {s['keyframes_sent']} keyframes; "
        f"inferences: {s['inferences']:,}. On the operator side, IK runs only when a new "
        f"stimulus arrives: {s['operator_ik_skipped_per_s']:.1f} control cycles per second "
        f"skip it ({s['operator_ik_saved_us_per_s']:.0f} us/s), with no error by construction "
        "(same input, same goals). "
        f"The unchanged-stimulus skip is the dead band ({s['deadband_n']} N): its cost is at "
        "most the dead band, by design, and never a different set of pressed cells. "
        f"The rate cap ({s['publish_rate_hz']:g} Hz of {s['rate_hz']:g} Hz) is not free: "
        "the frame it drops can differ from the one before it, for at most one frame "
        "period.",
        "",
        f"![skipping]({IMG_DIR}/bench_skipping.png)",
    ]
    return out


def figure(result: dict[str, Any], path: Path) -> Path:
    plt = pyplot()
    rows = [r for r in result["rows"] if r["kind"] != "published"]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    names = [r["kind"].replace("_", " ") for r in rows]
    axes[0].barh(names, [r["cpu_saved_us_per_s"] / 1e3 for r in rows])
    axes[0].set_xlabel("CPU saved (ms per second of scene)")
    axes[0].set_title(f"work saved in the {result['scene']} scene")
    diffs = [r["max_servo_counts_diff"] for r in rows]
    axes[1].barh(names, diffs, color=["#c44e52" if d else "#55a868" for d in diffs])
    for y, (d, r) in enumerate(zip(diffs, rows, strict=True)):
        axes[1].annotate(
            f" {d} counts, {r['max_abs_diff_n']:.3f} N",
            (max(d, 0), y),
            va="center",
            fontsize=8,
        )
    axes[1].set_xscale("symlog", linthresh=1)
    axes[1].set_xlabel("largest servo goal difference (counts; 1 count = 0.088 deg)")
    axes[1].set_title("error it costs")
    for ax in axes:
        ax.grid(alpha=0.3, axis="x")
    return save_figure(fig, path)


SECTION = Section(
    name="skipping",
    title=TITLE,
    sizes=SIZES,
    measure=measure,
    markdown=markdown,
    figure=figure,
)
