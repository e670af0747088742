"""Skipping: work the nodes do not do in the demo's scene, and what it would have changed.

The demo's scripted sensor is replayed frame by frame in virtual time (the
same pad model, seed, tare and grasp script as ``ScriptedTactileSensor``),
through the node's own ``FramePipeline.offer`` (as its loop offers each
frame), the node handed a virtual clock and a capture link, so the rate
cap, the no-contact and identical-frame skips, the dead band and the
keyframes behave as in the live node, and a 27 s scene costs a second or two.

Beside the node runs a shadow that never skips: every frame classified and
rendered by a second ``FramePipeline`` that forgets each frame before the
next. After each frame, what the operator is rendering (the last stimulus
sent) is compared with what the shadow would have sent: in newtons, in
which cells press, and in servo counts after IK. Zero difference is the
goal for the skips; the rate cap's difference is the price of rendering 60
of the 120 frames per second.

As a bench section: skipping work (no contact, identical frames, dead band,
rate cap) against its error.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from common.clocks.clock import VirtualClock
from common.wire.transport import CaptureLink
from deploy.scene import load_scene
from harness.bench.fmt import IMG_DIR, num, pyplot, results_of, save_figure, table
from harness.bench.scene_frames import demo_frames
from harness.bench.section import Context, Results, Section
from operator_side.palm.renderer import LinkGlideRenderer
from operator_side.servos.calibration import LinkGlideCalibration
from robot_side.node import FramePipeline, RobotNode

log = logging.getLogger(__name__)


class Shadow:
    """What the node would send for each frame if it never skipped anything.

    The node's own ``FramePipeline`` (so the compiled frame step where the
    node has one, with the node's arithmetic: its downsizing product sums in
    float64, NumPy's in float32, a few 1e-7 N that are not a skip's cost),
    told to forget the last frame and the last stimulus before each one.
    """

    def __init__(self, config: Any, classifier: Any) -> None:
        self.clock = VirtualClock()
        self.pipeline = FramePipeline(
            config, classifier, lambda msg: b"", now=self.clock, session=1
        )

    def stimulus(self, frame: np.ndarray, truth: Any) -> np.ndarray:
        from robot_side.tactile.base import TactileSample

        self.pipeline.resend_next()
        self.clock.advance(1)
        seq = self.clock.t_ns  # one per frame
        sample = TactileSample(frame=frame, seq=seq, t_capture_ns=self.clock.t_ns, truth=truth)
        return self.pipeline.process(sample).stimulus


#: what a frame's counters say the node did with it
_KIND_OF_COUNTER = (
    ("frames_skipped_rate", "rate_cap"),
    ("frames_no_contact", "no_contact"),
    ("frames_identical", "identical_frame"),
    ("stimuli_unchanged", "unchanged_stimulus"),
    ("stimuli_published", "published"),
)


def through_node(
    config: Any, classifier: Any, frames: list[np.ndarray], truths: list[Any], rate_hz: float
) -> tuple[RobotNode, CaptureLink, list[tuple[list[str], np.ndarray, np.ndarray]]]:
    """The frames at ``rate_hz`` in virtual time through the node's ``FramePipeline.offer``,
    as the node's loop offers them (rate cap included).

    Returns the node, its capture link, and per frame (what the node did with
    it, the stimulus the operator renders after it, what the shadow renders).
    """
    from robot_side.tactile.base import TactileSample

    clock = VirtualClock()
    link = CaptureLink()
    node = RobotNode(config, tactile=None, classifier=classifier, now=clock, link=link)
    shadow = Shadow(config, classifier)
    period = round(1e9 / rate_hz)
    out = []
    for i, (frame, truth) in enumerate(zip(frames, truths, strict=True)):
        clock.advance(period)
        before = dict(node.counters)
        sample = TactileSample(frame=frame, seq=i + 1, t_capture_ns=clock.t_ns, truth=truth)
        node.pipeline.offer(sample, clock.t_ns)
        after = node.counters
        kinds = [kind for c, kind in _KIND_OF_COUNTER if after[c] > before.get(c, 0)]
        msg = node.last_stimulus
        current = msg.stimulus if msg is not None else np.zeros((3, 3), np.float32)
        out.append((kinds, current, shadow.stimulus(frame, truth)))
    return node, link, out


def skipping(
    classifier: Any, stage_medians_us: dict[str, float], cycles: float, scene_name: str = "demo"
) -> dict[str, Any]:
    """Counts, frames per second and CPU saved per skip, and the output difference each causes."""
    scene = load_scene(scene_name)
    config = scene.robot
    frames, truths, rate_hz = demo_frames(scene_name, cycles)
    renderer = LinkGlideRenderer(scene.operator.renderer, LinkGlideCalibration())
    render = config.render
    kinds = ("rate_cap", "no_contact", "identical_frame", "unchanged_stimulus", "published")
    diff = {k: {"frames": 0, "max_abs_n": 0.0, "cells_differ": 0, "max_counts": 0} for k in kinds}
    counts_cache: dict[bytes, np.ndarray] = {}

    def counts_of(stim: np.ndarray) -> np.ndarray:
        key = stim.tobytes()
        if key not in counts_cache:
            counts_cache[key] = renderer.target_counts(stim)
        return counts_cache[key]

    node, link, per_frame = through_node(config, classifier, frames, truths, rate_hz)
    for kinds_here, current, full in per_frame:
        for kind in kinds_here:
            # the no-contact skip leaves out the classifier: compare what the node
            # computed (all zeros) with what classifying would have rendered
            got = np.zeros((3, 3), np.float32) if kind == "no_contact" else current
            d = diff[kind]
            d["frames"] += 1
            d["max_abs_n"] = max(d["max_abs_n"], float(np.abs(got - full).max()))
            d["cells_differ"] += int(not np.array_equal(got > 0, full > 0))
            d["max_counts"] = max(
                d["max_counts"], int(np.abs(counts_of(got) - counts_of(full)).max())
            )
    duration_s = len(frames) / rate_hz
    sent = link.messages
    keyframes = sum(1 for m in sent if m.keyframe)
    m = stage_medians_us
    render_us = m.get("render", 0.0)
    link_us = sum(
        m.get(k, 0.0)
        for k in (
            "encode",
            "zmq_transit_tcp",
            "decode",
            "ik_3_linkages",
            "counts_rate_limit",
            "servo_packet",
        )
    )
    saved_us = {
        "rate_cap": m.get("sanitize_contact", 0.0) + m.get("classification", 0.0) + render_us,
        "no_contact": m.get("classification", 0.0) + render_us,
        "identical_frame": m.get("classification", 0.0) + render_us,
        "unchanged_stimulus": link_us,
        "published": 0.0,
    }
    rows = []
    for kind in kinds:
        d = diff[kind]
        rows.append(
            {
                "kind": kind,
                "frames": d["frames"],
                "frames_per_s": d["frames"] / duration_s,
                "cpu_saved_us_per_frame": saved_us[kind],
                "cpu_saved_us_per_s": d["frames"] / duration_s * saved_us[kind],
                "max_abs_diff_n": d["max_abs_n"],
                "frames_with_other_cells": d["cells_differ"],
                "max_servo_counts_diff": d["max_counts"],
            }
        )
    palm_steps = duration_s * scene.operator.renderer.palm_step_rate_hz
    return {
        "scene": scene_name,
        "frames": len(frames),
        "duration_s": duration_s,
        "rate_hz": rate_hz,
        "publish_rate_hz": config.publish_rate_hz,
        "deadband_n": render.deadband_n,
        "render_mode": render.mode,
        "stimuli_sent": len(sent) - keyframes,
        "keyframes_sent": keyframes,
        "inferences": node.counters["inferences"],
        "rows": rows,
        "operator_ik_skipped_per_s": max(0.0, palm_steps - len(sent)) / duration_s,
        "operator_ik_saved_us_per_s": max(0.0, palm_steps - len(sent))
        / duration_s
        * m.get("ik_3_linkages", 0.0),
        "counters": {k: int(v) for k, v in node.counters.items()},
    }


TITLE = "Run time against error: skipping work"


@dataclass(frozen=True)
class SkippingSizes:
    skip_cycles: float  # of the demo scene's scripted grasps


SIZES = {
    "full": SkippingSizes(skip_cycles=2.0),
    "quick": SkippingSizes(skip_cycles=0.2),
    "smallest": SkippingSizes(skip_cycles=0.05),
}


def measure(ctx: Context, sizes: SkippingSizes) -> dict[str, Any]:
    """Savings counted at the paced stage medians (empty when the stages section was skipped)."""
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
        f"stimulus arrives: {s['operator_ik_skipped_per_s']:.1f} palm steps per second "
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
