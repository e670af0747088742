"""The robot node's compiled frame step publishes what its plain path publishes."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

pytest.importorskip("numba")

from common.clocks.clock import VirtualClock
from common.tactile.stimulus import render_cells, sanitize_with_peak
from common.wire.transport import CaptureLink
from harness.bench.fixtures import frame_set
from robot_side.node import RobotNode
from robot_side.node.compiled_step import CompiledFrameStep
from robot_side.node.config import RobotConfig
from robot_side.perception import load_classifier
from robot_side.tactile.base import TactileSample
from robot_side.tactile.scripted import ScriptedTactileSensor

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def classifier():
    return load_classifier(backend="numba")


def _node(classifier, compiled: bool, order: str) -> tuple[RobotNode, CaptureLink]:
    config = RobotConfig()
    config.render.compiled_step = compiled
    config.render.order = order
    link = CaptureLink()
    clock = VirtualClock(t_ns=0)  # every frame captured now: none is stale
    node = RobotNode(config, ScriptedTactileSensor(), classifier=classifier, now=clock, link=link)
    assert node.uses_compiled_step == compiled
    return node, link


def _garbage(rng: np.random.Generator, frame: np.ndarray) -> np.ndarray:
    bad = frame.copy()
    idx = rng.integers(0, 200, 5)
    bad.reshape(-1)[idx] = rng.choice([np.nan, np.inf, -np.inf, -3.0, 40.0], 5)
    return bad


@pytest.mark.parametrize("order", ["mask_then_peak", "peak_then_mask"])
def test_both_paths_publish_the_same_stimuli(classifier, order: str) -> None:
    """Every pattern and grip level, repeated frames, no-contact frames and sensor garbage."""
    fs = frame_set(1, seed=11)
    rng = np.random.default_rng(0)
    frames: list[np.ndarray] = []
    for k in rng.permutation(len(fs)):
        f = fs.frames[k]
        frames.append(f)
        roll = rng.random()
        if roll < 0.15:
            frames.append(f.copy())  # the same frame again: skipped by both
        elif roll < 0.25:
            frames.append(np.zeros_like(f))  # released
        elif roll < 0.35:
            frames.append(_garbage(rng, f))
        elif roll < 0.40:
            frames.append(f.astype(np.float64)[:, ::-1, :])  # another dtype, strided
    (plain, plain_sent), (compiled, compiled_sent) = (
        _node(classifier, False, order),
        _node(classifier, True, order),
    )
    for seq, frame in enumerate(frames, start=1):
        sample = TactileSample(frame=frame, seq=seq, t_capture_ns=0)
        for node in (plain, compiled):
            node.process(sample)
    assert len(plain_sent.messages) == len(compiled_sent.messages) > len(fs) // 2
    for a, b in zip(plain_sent.messages, compiled_sent.messages, strict=True):
        assert (a.frame_seq, a.pattern, a.contact) == (b.frame_seq, b.pattern, b.contact)
        np.testing.assert_allclose(a.stimulus, b.stimulus, atol=2e-6)
        assert np.array_equal(a.stimulus > 0, b.stimulus > 0)
        assert a.confidence == pytest.approx(b.confidence, abs=1e-6)
    keys = ("frames_no_contact", "frames_identical", "inferences", "stimuli_unchanged")
    assert {k: plain.counters[k] for k in keys} == {k: compiled.counters[k] for k in keys}
    assert compiled.counters["frames_identical"] > 0 and compiled.counters["frames_no_contact"] > 0


@settings(max_examples=200, deadline=None)
@given(
    arrays(
        np.float32,
        (2, 10, 10),
        elements=st.one_of(st.floats(0, 9, width=32), st.floats(width=32)),
    )
)
def test_any_frame_gives_the_plain_paths_bounded_output(classifier, frame: np.ndarray) -> None:
    step = CompiledFrameStep(
        classifier.numba_forward,
        method="antialiased",
        order="mask_then_peak",
        contact_threshold_n=1.0,
    )
    r = step.step(frame)
    clean, peak = sanitize_with_peak(frame)
    np.testing.assert_array_equal(step.sanitized, clean)
    assert r[CompiledFrameStep.PEAK] == peak
    if peak < 1.0:
        assert r[0] == CompiledFrameStep.NO_CONTACT
        return
    assert r[0] == CompiledFrameStep.RENDERED
    prediction = classifier.predict_one(clean)
    assert (int(r[2]), int(r[3])) == (prediction.angle, prediction.position)
    cells = r[CompiledFrameStep.CELLS :]
    assert all(np.isfinite(cells)) and min(cells) >= 0.0 and max(cells) <= 9.0
    np.testing.assert_allclose(cells, render_cells(clean, prediction.pattern), atol=2e-6)
    assert step.step(frame)[0] == CompiledFrameStep.IDENTICAL
    step.forget()
    assert step.step(frame)[0] == CompiledFrameStep.RENDERED
