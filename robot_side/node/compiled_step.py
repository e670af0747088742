"""The robot node's work on one frame in mask mode, as one compiled call (numba).

Why: between two sensor frames the core runs other work, so each frame
meets cold caches, and then a frame costs what its calls cost, not its
arithmetic. The node's plain path makes about a dozen NumPy and compiled
calls per frame (range check, peak, the identical-frame test, the
classifier, the downsizing product); this step makes one, about 160 us less
per frame paced on the development VM (docs/benchmarks.md).

It is the same computation as the plain path (``RobotNode`` falls back to
it whenever this step does not apply), with one difference: the 9 x 200
downsizing product sums in float64 before rounding to float32, where NumPy
sums in float32, so a cell can differ by a few 1e-7 N
(tests/robot/test_compiled_step.py checks both paths frame by frame).

Used when the classifier runs on the numba backend and the node renders
with the classifier's mask; ``render.compiled_step = false`` turns it off.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from common.tactile.contract import (
    FRAME_SHAPE,
    N_ANGLES,
    N_POSITIONS,
    SATURATION_N,
    STIMULUS_SHAPE,
    pattern_of,
)
from common.tactile.stimulus import downsizing_matrix, mask_columns
from robot_side.jit.cache import njit
from robot_side.perception.numba_forward import classify_frame

#: ``step``'s first value
NO_CONTACT, IDENTICAL, RENDERED = 0, 1, 2
#: where ``step``'s values sit: status, peak, angle, position, 4 + 3 probabilities, 9 cells
PEAK, ANGLE, POSITION, PROBS, CELLS = 1, 2, 3, 4, 11
_N_RESULT = CELLS + 9
_COLS = STIMULUS_SHAPE[1]  # cell (r, c) of the stimulus is cells[_COLS * r + c]


@njit()
def _frame_step(
    frame,
    clean,
    last,
    state,
    net,
    logits,
    n_angle,
    probs,
    matrix,
    mask_cols,
    mask_first,
    threshold,
    max_n,
    result,
):  # pragma: no cover - compiled
    # sanitize: a taxel outside [0, max_n] (NaN included) sends the frame through the cleaner
    in_range = True
    for c in range(2):
        for i in range(10):
            for j in range(10):
                v = frame[c, i, j]
                clean[c, i, j] = v
                if not (v >= 0.0 and v <= max_n):
                    in_range = False
    if not in_range:
        for c in range(2):
            for i in range(10):
                for j in range(10):
                    v = clean[c, i, j]
                    if not np.isfinite(v):
                        v = 0.0
                    clean[c, i, j] = min(max(v, 0.0), max_n)
    peak = clean[0, 0, 0]
    for c in range(2):
        for i in range(10):
            for j in range(10):
                peak = max(peak, clean[c, i, j])
    result[PEAK] = peak
    if not peak >= threshold:
        result[0] = NO_CONTACT
        state[0] = 0
        return
    if state[0] == 1:
        same = True
        for c in range(2):
            for i in range(10):
                for j in range(10):
                    if clean[c, i, j] != last[c, i, j]:
                        same = False
        if same:
            result[0] = IDENTICAL
            return
    last[:] = clean
    state[0] = 1
    w1, b1, w2, b2, heads, biases, pad1, pad2, acc, scratch = net
    classify_frame(
        clean, w1, b1, w2, b2, heads, biases, pad1, pad2, acc, scratch, logits, n_angle, probs
    )
    result[ANGLE] = probs[0]
    result[POSITION] = probs[1]
    for k in range(2, probs.shape[0]):
        result[PROBS + k - 2] = probs[k]
    angle, position = int(probs[0]), int(probs[1])
    flat = clean.reshape(200)
    cells = np.zeros(9)
    for k in range(9):
        s = 0.0
        for t in range(200):
            s += np.float64(matrix[k, t]) * np.float64(flat[t])
        cells[k] = min(max(np.float64(np.float32(s)), 0.0), max_n)
    for k in range(9):
        result[CELLS + k] = 0.0
    for r in range(3):
        col = mask_cols[angle, position, r]
        if col < 0:
            continue
        best = col
        if not mask_first:  # the paper's order: the row's peak, kept only on the mask's cell
            best = 0
            for c in range(1, 3):
                if cells[_COLS * r + c] > cells[_COLS * r + best]:
                    best = c
            if best != col:
                continue
        result[CELLS + _COLS * r + best] = cells[_COLS * r + best]
    result[0] = RENDERED


class CompiledFrameStep:
    """Sanitize, contact, identical-frame test, classify and render one frame in one call.

    Owns its work buffers (the classifier's own are left to ``predict_one``), so
    only the node's loop may call it.
    """

    NO_CONTACT, IDENTICAL, RENDERED = NO_CONTACT, IDENTICAL, RENDERED
    PEAK, ANGLE, POSITION, PROBS, CELLS = PEAK, ANGLE, POSITION, PROBS, CELLS

    def __init__(
        self, forward: Any, *, method: str, order: str, contact_threshold_n: float
    ) -> None:
        self._net = forward.kernel_args()
        self._n_angle = forward.n_angle
        self._logits = np.zeros(forward.n_logits, np.float32)
        self._probs = np.zeros(2 + forward.n_logits, np.float64)
        self._matrix = np.ascontiguousarray(downsizing_matrix(method), np.float32)
        self._mask_cols = np.array(  # by (angle class, position class): no encoding here
            [
                [
                    [-1 if c is None else c for c in mask_columns(pattern_of(a, p))]
                    for p in range(N_POSITIONS)
                ]
                for a in range(N_ANGLES)
            ],
            np.int64,
        )
        self._mask_first = order == "mask_then_peak"
        self._threshold = float(contact_threshold_n)
        self.sanitized = np.zeros(FRAME_SHAPE, np.float32)
        self._last = np.zeros(FRAME_SHAPE, np.float32)
        self._state = np.zeros(1, np.int64)
        self._result = np.zeros(_N_RESULT, np.float64)
        self.step(np.zeros(FRAME_SHAPE, np.float32))  # compile or load the cache now
        self.forget()

    @classmethod
    def for_node(cls, classifier: Any, render: Any) -> CompiledFrameStep | None:
        """The step for this classifier and render config, or None where it does not apply."""
        forward = getattr(classifier, "numba_forward", None)
        if forward is None or render.mode != "mask" or not render.compiled_step:
            return None
        return cls(
            forward,
            method=render.method,
            order=render.order,
            contact_threshold_n=render.contact_threshold_n,
        )

    def step(self, frame: np.ndarray) -> list[float]:
        """[status, peak, angle, position, *probabilities, *cells]; ``sanitized`` holds the frame.

        Status: ``NO_CONTACT`` (the rest but the peak is stale), ``IDENTICAL`` (the
        same frame as the last classified one: nothing new), ``RENDERED``.
        """
        x = frame
        if (
            type(x) is not np.ndarray
            or x.dtype != np.float32
            or x.shape != FRAME_SHAPE
            or not (x.flags.c_contiguous and x.flags.writeable)
        ):  # one argument type only: anything else would compile a new signature
            x = np.array(frame, dtype=np.float32)
            if x.shape != FRAME_SHAPE:
                raise ValueError(f"a frame has shape {FRAME_SHAPE}, not {x.shape}")
        _frame_step(
            x, self.sanitized, self._last, self._state, self._net, self._logits,
            self._n_angle, self._probs, self._matrix, self._mask_cols, self._mask_first,
            self._threshold, SATURATION_N, self._result,
        )  # fmt: skip
        return self._result.tolist()

    def forget(self) -> None:
        """The next frame is classified and rendered even if it equals the last one."""
        self._state[0] = 0
