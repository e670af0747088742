"""The node, replay and the skipping bench apply one frame rule, so they agree frame by frame.

Every frame is rendered here (no rate cap: ``process``);
tests/robot/test_frame_pipeline_agreement.py offers frames as the node's
loop does, rate cap included.
"""

from __future__ import annotations

import numpy as np
import pytest

from common.clocks.clock import VirtualClock
from common.recording.mcap_recorder import node_recorder
from common.wire.transport import CaptureLink
from deploy import replay
from harness.bench.fixtures import frame_set
from harness.bench.skipping import Shadow
from robot_side.node import RobotNode
from robot_side.node.config import RobotConfig
from robot_side.perception import load_classifier
from robot_side.tactile.base import GraspTruth, TactileSample

pytestmark = [pytest.mark.slow, pytest.mark.untimed]  # no timing checked

PERIOD_NS = 8_333_333  # 120 Hz


def _frames() -> tuple[list[np.ndarray], list[GraspTruth]]:
    """Every pattern; repeats, moves inside the dead band and releases; grasps held still."""
    fs = frame_set(1, seed=4)
    rng = np.random.default_rng(1)
    frames, truths = [], []
    for k in rng.permutation(len(fs))[:120]:
        truth = GraspTruth(pattern=int(fs.pattern[k]), grip_level=None)
        roll = rng.random()
        repeats = 6 if roll < 0.1 else 2 if roll < 0.3 else 1
        frames += [fs.frames[k]] * repeats
        truths += [truth] * repeats
        if 0.3 <= roll < 0.5:  # moved by less than the dead band
            frames.append(fs.frames[k] + np.float32(0.002))
            truths.append(truth)
        if roll > 0.9:
            frames.append(np.zeros_like(fs.frames[k]))
            truths.append(GraspTruth(pattern=None, grip_level=None))
    return frames, truths


@pytest.fixture(scope="module")
def classifier():
    return load_classifier(backend="numpy")  # the plain path, where render_frame runs


@pytest.mark.parametrize("mode", ["direct", "mask", "mask_ground_truth"])
def test_node_replay_and_bench_agree_on_every_frame(tmp_path, classifier, mode: str) -> None:
    config = RobotConfig()
    config.render.mode = mode
    config.render.keyframe_interval_ms = 30.0  # a held grasp sends keyframes
    config.publish_rate_hz = 1000.0  # every 120 Hz frame is rendered: replay's cap agrees
    path = tmp_path / "robot.mcap"
    recorder = node_recorder(path, config, "robot")
    clock = VirtualClock()
    link = CaptureLink()
    node = RobotNode(config, None, classifier=classifier, recorder=recorder, now=clock, link=link)
    assert not node.uses_compiled_step
    frames, truths = _frames()
    shadow = Shadow(config, classifier)
    for seq, (frame, truth) in enumerate(zip(frames, truths, strict=True), start=1):
        clock.advance(PERIOD_NS)
        node.process(TactileSample(frame=frame, seq=seq, t_capture_ns=clock(), truth=truth))
        # the bench's shadow renders every frame afresh; the node's current stimulus is
        # the same within the dead band (exactly the same for a frame it just sent)
        full = shadow.stimulus(frame, truth)
        current = node.last_stimulus
        assert current is not None
        if current.frame_seq == seq and not current.keyframe:
            np.testing.assert_array_equal(current.stimulus, full)
        else:
            assert np.abs(current.stimulus - full).max() <= config.render.deadband_n
    recorder.close()
    sent = [m for m in link.messages if not m.keyframe]
    keyframes = len(link.messages) - len(sent)
    assert keyframes > 0 and node.counters["stimuli_unchanged"] > 0

    summary = replay.check(path)
    assert summary["mismatches"] == 0, summary["examples"]
    assert summary["checked"]["frames_replayed"] == len(frames)
    assert summary["checked"]["stimuli_matching"] == len(sent)
    assert summary["checked"]["keyframes_matching"] == keyframes
    if mode == "mask":  # the recorded predictions instead of the classifier: the same
        summary = replay.check(path, use_classifier=False)
        assert summary["mismatches"] == 0, summary["examples"]
        assert summary["checked"]["stimuli_matching"] == len(sent)


def test_replay_reports_a_stimulus_the_dead_band_would_have_held_back(tmp_path) -> None:
    """Replay runs the node's dead band: a stimulus sent for a change inside it is a mismatch."""
    config = RobotConfig()
    config.render.mode = "direct"
    config.render.deadband_n = 0.0
    config.publish_rate_hz = 1000.0  # both frames rendered, 8 ms apart
    path = tmp_path / "robot.mcap"
    recorder = node_recorder(path, config, "robot")
    clock = VirtualClock()
    node = RobotNode(config, None, recorder=recorder, now=clock, link=CaptureLink())
    frame = frame_set(1, seed=4).frames[0]
    for seq in (1, 2):
        clock.advance(PERIOD_NS)
        nudged = frame + np.float32(0.01 * seq)  # moves every cell by ~0.01 N
        node.process(TactileSample(frame=nudged, seq=seq, t_capture_ns=clock()))
    recorder.close()
    assert node.counters["stimuli_published"] == 2
    assert replay.check(path)["mismatches"] == 0
    stricter = tmp_path / "stricter.mcap"
    _with_config(path, stricter, "deadband_n = 0.0", "deadband_n = 0.05")
    assert replay.check(stricter)["mismatch_kinds"] == {"stimulus": 1}


def _with_config(src, dst, old: str, new: str) -> None:
    from common.recording.mcap_recorder import McapRecorder, read_metadata, read_recording

    meta = read_metadata(src)
    text = meta["deepxpalm.node"]["config_toml"]
    assert old in text
    node_meta = {**meta["deepxpalm.node"], "config_toml": text.replace(old, new)}
    with McapRecorder(dst, metadata={"deepxpalm.node": node_meta}) as rec:
        for channel, t, record in read_recording(src):
            record.pop("decoded", None)
            rec.write(channel, t, record)
