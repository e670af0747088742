"""The node, replay and the skipping bench drive one FramePipeline: they agree, rate cap included.

The same 120 Hz frames go through the node's path (``pipeline.offer`` at each
frame's arrival, as the node's loop offers it, recording as the live node
records), the bench's (``harness.bench.skipping.through_node``) and replay's
(``deploy.replay.check`` on the node's recording). With ``publish_rate_hz``
at 60 the cap skips about every other frame; all three must send the same
stimuli for the same frames and skip the same frames.
"""

from __future__ import annotations

import numpy as np
import pytest

from common.clocks.clock import VirtualClock
from common.recording.mcap_recorder import node_recorder
from common.wire.transport import CaptureLink
from deploy import replay
from harness.bench.fixtures import frame_set
from harness.bench.skipping import through_node
from robot_side.node import RobotNode
from robot_side.node.config import RobotConfig
from robot_side.perception import load_classifier
from robot_side.tactile.base import GraspTruth, TactileSample

RATE_HZ = 120.0
PERIOD_NS = round(1e9 / RATE_HZ)


def _grasps() -> tuple[list[np.ndarray], list[GraspTruth]]:
    """Grasps held for 3 to 30 frames (still or trembling), each followed by a release."""
    fs = frame_set(1, seed=9)
    rng = np.random.default_rng(3)
    frames, truths = [], []
    for k in rng.permutation(len(fs))[:40]:
        truth = GraspTruth(pattern=int(fs.pattern[k]), grip_level=None)
        trembling = rng.random() < 0.5
        for i in range(int(rng.integers(3, 31))):
            nudge = np.float32(0.003 * (i % 3)) if trembling else np.float32(0.0)
            frames.append(fs.frames[k] + nudge)
            truths.append(truth)
        for _ in range(int(rng.integers(1, 5))):
            frames.append(np.zeros_like(fs.frames[k]))
            truths.append(GraspTruth(pattern=None, grip_level=None))
    return frames, truths


def _wire(messages: list) -> list[tuple]:
    return [(m.frame_seq, m.keyframe, m.contact, m.pattern, m.stimulus.tobytes()) for m in messages]


@pytest.fixture(scope="module")
def classifier():
    return load_classifier(backend="numpy")


@pytest.mark.parametrize("mode", ["direct", "mask"])
def test_node_bench_and_replay_skip_and_send_the_same(tmp_path, classifier, mode: str) -> None:
    config = RobotConfig()
    config.render.mode = mode
    config.render.keyframe_interval_ms = 40.0  # held grasps send keyframes
    assert config.publish_rate_hz == 60.0  # half the frames' rate: the cap bites
    frames, truths = _grasps()

    # the node's path, recorded as the live node records
    path = tmp_path / "robot.mcap"
    recorder = node_recorder(path, config, "robot")
    clock, link = VirtualClock(), CaptureLink()
    node = RobotNode(config, None, classifier=classifier, recorder=recorder, now=clock, link=link)
    for seq, (frame, truth) in enumerate(zip(frames, truths, strict=True), start=1):
        clock.advance(PERIOD_NS)
        sample = TactileSample(frame=frame, seq=seq, t_capture_ns=clock(), truth=truth)
        node.pipeline.offer(sample, clock())
    recorder.close()
    counters = node.counters
    capped, rendered = counters["frames_skipped_rate"], counters["frames_processed"]
    assert capped + rendered == len(frames)
    assert abs(capped - rendered) <= 1, "at 60 of 120 Hz every other frame is skipped"
    for skip in ("frames_no_contact", "frames_identical", "stimuli_unchanged", "keyframes"):
        assert counters[skip] > 0, f"the sequence never exercised {skip}"

    # the bench's path: the same frames, the same sends, the same skips
    bench_node, bench_link, per_frame = through_node(config, classifier, frames, truths, RATE_HZ)
    assert _wire(bench_link.messages) == _wire(link.messages)
    assert sum("rate_cap" in kinds for kinds, _, _ in per_frame) == capped
    for name in ("frames_skipped_rate", "frames_processed", "stimuli_published", "keyframes"):
        assert bench_node.counters[name] == counters[name], name

    # replay: every recorded frame within the cap, every stimulus and keyframe the same
    sent = [m for m in link.messages if not m.keyframe]
    summary = replay.check(path)
    assert summary["mismatches"] == 0, summary["examples"]
    assert summary["checked"]["frames_replayed"] == rendered
    assert summary["checked"]["stimuli_matching"] == len(sent)
    assert summary["checked"]["keyframes_matching"] == len(link.messages) - len(sent)


def test_replay_reports_frames_rendered_faster_than_the_rate_cap(tmp_path) -> None:
    """A node that rendered every 120 Hz frame under a 60 Hz cap: replay names each extra one."""
    config = RobotConfig()
    config.render.mode = "direct"
    path = tmp_path / "robot.mcap"
    recorder = node_recorder(path, config, "robot")
    clock = VirtualClock()
    node = RobotNode(config, None, recorder=recorder, now=clock, link=CaptureLink())
    frames, _ = _grasps()
    for seq, frame in enumerate(frames[:40], start=1):
        clock.advance(PERIOD_NS)
        node.process(TactileSample(frame=frame, seq=seq, t_capture_ns=clock()))  # no cap
    recorder.close()
    summary = replay.check(path)
    assert summary["mismatch_kinds"].get("rate_cap") == 20, summary["mismatch_kinds"]
