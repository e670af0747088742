"""The rule for one frame: sanitized frame -> contact -> pattern -> the nine cells sent.

``render_frame`` is the rule itself; ``FrameRenderer`` applies it to the
node's frames, with the two skips that cannot change its output (no
classifier without contact, nothing recomputed for an identical frame),
on the plain path or in one compiled call (compiled_step.py).
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from common.recording.channels import Recorder
from common.tactile.contract import pattern_of
from common.tactile.stimulus import NO_CELLS, Method, Order, render_cells, sanitize_with_peak
from robot_side.node.config import RenderConfig
from robot_side.tactile.base import TactileSample

log = logging.getLogger(__name__)

#: (contact, cells, pattern, confidence) of a rendered frame
Rendered = tuple[bool, list[float], int | None, float | None]


class RenderSettings(Protocol):
    """What ``render_frame`` reads of ``robot_side.node.config.RenderConfig``."""

    mode: str
    method: Method
    order: Order


class Prediction(Protocol):
    pattern: int
    confidence: float
    angle_probs: tuple[float, ...]
    position_probs: tuple[float, ...]


class Classifier(Protocol):
    """What the node needs of robot_side.perception.TiltClassifier (no import of it here)."""

    def predict_one(self, frame: np.ndarray) -> Prediction: ...


def render_frame(
    frame: np.ndarray,
    contact: bool,
    render: RenderSettings,
    *,
    classify: Callable[[np.ndarray], int] | None = None,
    truth: int | None = None,
) -> tuple[list[float], int | None]:
    """The rule for one frame: (the nine cells sent, the pattern they were rendered with).

    ``frame`` is sanitized and ``contact`` its contact test. Without contact
    nothing is pressed and nothing is classified. The mode picks the mask:
    ``mask`` the classifier's (``classify`` is called only then),
    ``mask_ground_truth`` the simulator's ``truth``, ``direct`` none. A mask
    mode without a pattern (nothing held) presses nothing.
    """
    if not contact:
        return list(NO_CELLS), None
    mode = render.mode
    if mode == "direct":
        pattern = None
    else:
        pattern = classify(frame) if mode == "mask" else truth
        if pattern is None:
            return list(NO_CELLS), None
    return render_cells(frame, pattern, method=render.method, order=render.order), pattern


def compiled_step_for(classifier: Classifier | None, render: RenderConfig) -> Any:
    """``compiled_step.CompiledFrameStep`` where it applies (numba classifier, mask mode), or None.

    Here rather than in compiled_step.py: that module imports numba, which a
    node without the numba backend never needs.
    """
    if getattr(classifier, "numba_forward", None) is None:
        return None  # numba may not even be installed: import nothing
    try:
        from robot_side.node.compiled_step import CompiledFrameStep

        return CompiledFrameStep.for_node(classifier, render)
    except Exception as e:  # the plain path publishes the same stimuli, slower
        log.warning("compiled frame step unavailable (%s); using the plain path", e)
        return None


class FrameRenderer:
    """``render_frame`` on the node's frames, skipping what cannot change its output."""

    def __init__(
        self,
        render: RenderConfig,
        classifier: Classifier | None,
        counters: Counter[str],
        recorder: Recorder | None,
        now: Callable[[], int],
    ) -> None:
        self.render = render
        self.classifier = classifier
        #: mask mode on the numba classifier: one compiled call per frame (None otherwise)
        self.compiled = compiled_step_for(classifier, render)
        self.counters = counters
        self.recorder = recorder  # None: nothing recorded
        self.now = now
        self._last_frame: np.ndarray | None = None

    def forget(self) -> None:
        """Render the next frame afresh, even if it is the last one again."""
        self._last_frame = None
        if self.compiled is not None:
            self.compiled.forget()

    def rendered(self, sample: TactileSample, now: int, truth: int | None) -> Rendered | None:
        """(contact, cells, pattern, confidence), or None for the last frame again."""
        if self.compiled is not None:
            return self._compiled(sample, now)
        render = self.render
        frame, peak = sanitize_with_peak(sample.frame)
        if self.recorder is not None:
            self._record_frame(sample, frame, now)
        contact = peak >= render.contact_threshold_n  # is_contact, from the same pass
        if not contact:
            self.counters["frames_no_contact"] += 1
            self._last_frame = None
            return False, list(NO_CELLS), None, None
        if self._last_frame is not None and np.array_equal(frame, self._last_frame):
            return None
        self._last_frame = frame
        confidence: float | None = None

        def classify(f: np.ndarray) -> int:
            nonlocal confidence
            prediction = self.classifier.predict_one(f)
            confidence = min(max(prediction.confidence, 0.0), 1.0)
            self._count_inference(sample, prediction.angle_probs, prediction.position_probs,
                                  prediction.pattern, confidence)  # fmt: skip
            return prediction.pattern

        cells, pattern = render_frame(frame, True, render, classify=classify, truth=truth)
        if render.mode == "mask_ground_truth":
            confidence = 1.0 if truth is not None else None
        return True, cells, pattern, confidence

    def _compiled(self, sample: TactileSample, now: int) -> Rendered | None:
        """``rendered`` in mask mode through the one compiled call (compiled_step.py)."""
        step = self.compiled
        r = step.step(sample.frame)
        if self.recorder is not None:
            self._record_frame(sample, step.sanitized.copy(), now)
        status = r[0]
        if status == step.NO_CONTACT:
            self.counters["frames_no_contact"] += 1
            return False, list(NO_CELLS), None, None
        if status == step.IDENTICAL:
            return None
        angle, position = int(r[step.ANGLE]), int(r[step.POSITION])
        at = step.PROBS
        angle_probs = tuple(r[at : at + 4])
        position_probs = tuple(r[at + 4 : at + 7])
        pattern = pattern_of(angle, position)
        confidence = min(max(angle_probs[angle] * position_probs[position], 0.0), 1.0)
        self._count_inference(sample, angle_probs, position_probs, pattern, confidence)
        return True, r[step.CELLS : step.CELLS + 9], pattern, confidence

    def _record_frame(self, sample: TactileSample, frame: np.ndarray, now: int) -> None:
        self.recorder.write(
            "robot/frame",
            now,
            {"frame": frame, "frame_seq": sample.seq, "t_capture_ns": sample.t_capture_ns},
        )

    def _count_inference(
        self,
        sample: TactileSample,
        angle_probs: tuple[float, ...],
        position_probs: tuple[float, ...],
        pattern: int,
        confidence: float,
    ) -> None:
        self.counters["inferences"] += 1
        if self.recorder is not None:
            self.recorder.write(
                "robot/prediction",
                self.now(),
                {
                    "frame_seq": sample.seq,
                    "angle_probs": np.array(angle_probs, np.float32),
                    "position_probs": np.array(position_probs, np.float32),
                    "pattern": pattern,
                    "confidence": confidence,
                },
            )
