"""Section: glass-to-glass video latency, robot camera to the operator's browser."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from deploy.bench.fmt import results_of
from deploy.bench.section import Context, Results, Section, Verdict
from deploy.bench.video import STALL_MS, WARMUP_FRAMES

TITLE = "Video: glass to glass"

#: the goal for the median latency
P50_GOAL_MS = 80.0


@dataclass(frozen=True)
class VideoSizes:
    video_frames: int  # stamped frames read in the browser (30 a second)
    viewers_s: float  # four aiortc viewers at once, this long


SIZES = {
    "full": VideoSizes(video_frames=1200, viewers_s=60.0),
    "quick": VideoSizes(video_frames=300, viewers_s=20.0),
    "smallest": VideoSizes(video_frames=30, viewers_s=3.0),
}
VIEWERS = 4


def measure(ctx: Context, sizes: VideoSizes) -> dict[str, Any]:
    from deploy.bench.video import all_cores, glass_to_glass
    from deploy.bench.video_viewers import many_viewers

    out = glass_to_glass(sizes.video_frames)
    with all_cores():
        out["many_viewers"] = many_viewers(VIEWERS, sizes.viewers_s)
    return out


def verdicts(results: Results) -> list[Verdict]:
    """The goal stated in the section's own text."""
    s = results_of(results, "video")
    if s is None:
        return []
    lat = s["latency_ms"]
    return [
        Verdict(
            f"p50 under {P50_GOAL_MS:g} ms and no stall over {STALL_MS:g} ms",
            f"p50 {lat['p50']:.0f} ms, {s['stalls_over_500ms']} stalls",
            lat["p50"] < P50_GOAL_MS and s["stalls_over_500ms"] == 0,
            table=None,
        )
    ]


def markdown(results: Results) -> list[str]:
    """Nothing when the section did not run."""
    section = results_of(results, "video")
    if not section:
        return []
    lat = section["latency_ms"]
    (goal,) = verdicts(results)
    verdict = "passes" if goal.passed else "fails"
    return [
        "",
        f"## {TITLE}",
        "",
        f"The stamped test pattern ({section['width']}x{section['height']} at "
        f"{section['fps_source']:g} fps) from the robot's video server (aiortc, VP8, WebRTC "
        "on loopback) to the dashboard in headless chromium, which reads each presented "
        "frame's capture time back from its pixels (`deploy/bench/video.py`). "
        f"{section['frames']} frames after a {WARMUP_FRAMES}-frame warm-up; the goal is "
        f"{goal.what}: it {verdict}. Measured {section['date']}, "
        f"machine load (1 min) {section['load_before']['loadavg_1m']} before and "
        f"{section['load_after']['loadavg_1m']} after, on a machine shared with other work.",
        "",
        "| frames | p50 ms | p90 ms | p99 ms | max ms | presented fps | longest gap ms "
        "| stalls > 500 ms | frames not presented | sender CPU (share of a core) |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
        f"| {section['frames']} | {lat['p50']:.0f} | {lat['p90']:.0f} | {lat['p99']:.0f} | "
        f"{lat['max']:.0f} | {section['fps_presented']} | {section['longest_gap_ms']:.0f} | "
        f"{section['stalls_over_500ms']} | {section['skipped_frames']} | "
        f"{section.get('server_cpu_share', float('nan')):.2f} |",
        *_many_viewers(section.get("many_viewers")),
        "",
        "Not measured here: the link simulator scenarios (the `video_netsim` section plays "
        "the same page through them), and a real camera's exposure and USB transfer, which "
        "come before the stamp.",
    ]


def _many_viewers(m: dict[str, Any] | None) -> list[str]:
    if not m:
        return []
    return [
        "",
        f"{m['viewers']} viewers at once for {m['seconds']:g} s, the same pattern, each an "
        "aiortc receiver in the bench's process timing capture to decoded frame "
        f"(`deploy/bench/video_viewers.py`): p50 {m['p50_ms']} ms, p99 {m['p99_ms']} ms, "
        f"{m['fps_per_viewer']} fps for the slowest viewer, longest gap "
        f"{m['longest_gap_ms']:.0f} ms, {m['stalls_over_500ms']} stalls over 500 ms, "
        f"{m['ended_early']} viewers cut off; the machine's CPU was "
        f"{m['machine_idle_cpu']:.0%} idle.",
    ]


SECTION = Section(
    name="video",
    title=TITLE,
    sizes=SIZES,
    measure=measure,
    markdown=markdown,
    verdicts=verdicts,
)
