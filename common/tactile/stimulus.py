"""From a tactile frame to the 3x3 stimulus (docs/tactile.md, "Downsizing").

contact map (mean of both pads) -> bicubic downsizing to 3x3 -> keep the
peak of each row -> multiply by the recognised pattern's mask. The pad mean
and both downsizing weight matrices are one precomputed (9, 200) matrix, so
a frame costs one matrix-vector product (``downsizing_matrix``).

NumPy only and in ``common`` because both nodes render: the robot node every
frame (``robot_side.node.frame_pipeline``), the operator's
perception study each trial, exactly as the robot would.

The default is antialiased bicubic (the kernel widened by the scale factor,
as PIL's BICUBIC and torch's ``antialias=True``): every taxel contributes, so
a band between the sample points is not missed. ``plain`` bicubic (4 x 4 taps
per output, as torch's default) and ``area`` averaging stay for comparison.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from common.tactile.contract import (
    CONTACT_FLOOR_N,
    FRAME_SHAPE,
    MASKS_F32,
    SATURATION_N,
    STIMULUS_SHAPE,
)

#: the contract's names under the names ``robot_side/rendering.py`` still re-exports; nothing
#: else may use them (they go when rendering.py stops re-exporting this module)
CONTACT_THRESHOLD_N = CONTACT_FLOOR_N
SENSOR_MAX_N = SATURATION_N
_ROWS, _COLS = STIMULUS_SHAPE

Method = Literal["antialiased", "plain", "area"]
Order = Literal["peak_then_mask", "mask_then_peak"]
METHODS: tuple[str, ...] = ("antialiased", "plain", "area")
ORDERS: tuple[str, ...] = ("peak_then_mask", "mask_then_peak")
#: the stimulus of a frame without contact: every linkage lifted
NO_CELLS: tuple[float, ...] = (0.0,) * 9


def _cubic(x: np.ndarray, a: float) -> np.ndarray:
    """Keys' cubic convolution kernel."""
    x = np.abs(x)
    return np.where(
        x < 1,
        ((a + 2) * x - (a + 3)) * x * x + 1,
        np.where(x < 2, (((x - 5) * x + 8) * x - 4) * a, 0.0),
    )


def antialiased_bicubic_weights(n_in: int, n_out: int, a: float = -0.5) -> np.ndarray:
    """(n_out, n_in) weights: PIL's BICUBIC resampling for a reduction."""
    scale = n_in / n_out
    support = 2.0 * scale
    w = np.zeros((n_out, n_in))
    for i in range(n_out):
        center = (i + 0.5) * scale
        lo = max(0, int(np.floor(center - support)))
        hi = min(n_in, int(np.ceil(center + support)))
        j = np.arange(lo, hi)
        w[i, lo:hi] = _cubic((j + 0.5 - center) / scale, a)
        w[i] /= w[i].sum()
    return w


def plain_bicubic_weights(n_in: int, n_out: int, a: float = -0.75) -> np.ndarray:
    """(n_out, n_in) weights: 4 taps around each sample, edges replicated."""
    scale = n_in / n_out
    w = np.zeros((n_out, n_in))
    for i in range(n_out):
        src = (i + 0.5) * scale - 0.5
        base = int(np.floor(src))
        t = src - base
        for k in range(-1, 3):
            j = min(max(base + k, 0), n_in - 1)
            w[i, j] += _cubic(np.array(t - k), a)
    return w


def area_weights(n_in: int, n_out: int) -> np.ndarray:
    """(n_out, n_in) weights: the mean over each output cell's footprint."""
    scale = n_in / n_out
    w = np.zeros((n_out, n_in))
    for i in range(n_out):
        lo, hi = i * scale, (i + 1) * scale
        for j in range(n_in):
            w[i, j] = max(0.0, min(hi, j + 1) - max(lo, j))
        w[i] /= w[i].sum()
    return w


_WEIGHTS = {
    "antialiased": antialiased_bicubic_weights(10, 3),
    "plain": plain_bicubic_weights(10, 3),
    "area": area_weights(10, 3),
}


def _fused(w: np.ndarray) -> np.ndarray:
    """(9, 200): the mean of both pads and both downsizing products as one matrix.

    out[3 i + j] = sum over pads, rows k, columns l of
    0.5 * Wy[i, k] * Wx[j, l] * frame[pad, k, l], i.e. half of kron(Wy, Wx)
    applied to each pad: one matrix-vector product per frame.
    """
    k = 0.5 * np.kron(w, w)
    return np.ascontiguousarray(np.hstack([k, k]), dtype=np.float32)


_FUSED = {k: _fused(w) for k, w in _WEIGHTS.items()}
#: per pattern, per row: the mask's column in that row, or None
_MASK_COLS: list[list[int | None]] = [
    [next((c for c in range(3) if m[r, c]), None) for r in range(3)] for m in MASKS_F32 > 0
]


def downsizing_weights(method: Method) -> np.ndarray:
    """(3, 10) float64: one axis of the 10x10 -> 3x3 downsizing (the same for both axes)."""
    return _WEIGHTS[method].copy()


def downsizing_matrix(method: Method) -> np.ndarray:
    """(9, 200) float32: both pads' mean and the 10x10 -> 3x3 downsizing as one matrix."""
    return _FUSED[method]


def mask_columns(pattern: int) -> list[int | None]:
    """Per stimulus row, the column the pattern's mask keeps, or None for an empty row."""
    return list(_MASK_COLS[pattern])


def sanitize_frame(frame: np.ndarray) -> np.ndarray:
    """A ``FRAME_SHAPE`` float32 frame held to the sensor's range, whatever came in.

    Non-finite taxels read 0 N and nothing exceeds saturation, so neither the
    downsizing nor the classifier ever sees garbage. A frame already in range
    comes back as it is (no copy).
    """
    return sanitize_with_peak(frame)[0]


def sanitize_with_peak(frame: np.ndarray) -> tuple[np.ndarray, float]:
    """``sanitize_frame`` and the largest taxel of the result, in one pass over the frame.

    The robot node's prelude on every frame: what a driver delivers is almost
    always in range already, which one minimum and one maximum prove (a NaN
    fails both comparisons). Only a frame that fails is copied and cleaned.
    """
    frame = np.asarray(frame, dtype=np.float32)
    if frame.shape != FRAME_SHAPE:
        raise ValueError(f"a frame has shape {FRAME_SHAPE}, not {frame.shape}")
    lo, hi = float(frame.min()), float(frame.max())
    if lo >= 0.0 and hi <= SATURATION_N:
        return frame, hi
    if not np.isfinite(frame).all():
        frame = np.nan_to_num(frame, nan=0.0, posinf=0.0, neginf=0.0)
    frame = np.clip(frame, 0.0, SATURATION_N)
    return frame, float(frame.max())


def is_contact(frame: np.ndarray, threshold_n: float = CONTACT_FLOOR_N) -> bool:
    """A frame whose largest taxel reaches the threshold holds a grasp."""
    return bool(frame.max() >= threshold_n)


def render_stimulus(
    frame: np.ndarray,
    pattern: int | None,
    *,
    method: Method = "antialiased",
    order: Order = "mask_then_peak",
    contact_threshold_n: float = CONTACT_FLOOR_N,
) -> np.ndarray:
    """The 3x3 float32 stimulus for a ``FRAME_SHAPE`` frame in newtons.

    ``pattern=None`` is direct rendering (no mask, the paper's baseline).
    Readings are held to the sensor's range first: non-finite taxels count as
    0 N (a broken taxel must not poison a stimulus), and nothing reads above
    saturation, so no garbage can overflow the downsizing.
    """
    frame = sanitize_frame(frame)
    if not is_contact(frame, contact_threshold_n):
        return np.zeros((3, 3), dtype=np.float32)
    return render_contact(frame, pattern, method=method, order=order)


def render_contact(
    frame: np.ndarray,
    pattern: int | None,
    *,
    method: Method = "antialiased",
    order: Order = "mask_then_peak",
) -> np.ndarray:
    """``render_stimulus`` for a frame already sanitized and known to hold a contact."""
    cells = render_cells(frame, pattern, method=method, order=order)
    return np.array(cells, dtype=np.float32).reshape(3, 3)


def render_cells(
    frame: np.ndarray,
    pattern: int | None,
    *,
    method: Method = "antialiased",
    order: Order = "mask_then_peak",
) -> list[float]:
    """``render_contact`` as nine floats, row by row: the robot node's hot path.

    One (9 x 200) product, then the peak and mask over nine numbers in plain
    Python (NumPy's per-call cost dominates at this size). The cells are
    float32 values, so an array made from them equals ``render_contact``'s.
    """
    values = (_FUSED[method] @ frame.reshape(200)).tolist()
    out = [0.0] * 9
    cols = None if pattern is None else _MASK_COLS[pattern]
    for r in range(_ROWS):
        row = [min(max(v, 0.0), SATURATION_N) for v in values[_COLS * r : _COLS * (r + 1)]]
        if cols is None:
            c = row.index(max(row))
        elif cols[r] is None:
            continue
        elif order == "mask_then_peak":
            c = cols[r]
        else:
            c = row.index(max(row))
            if c != cols[r]:
                continue  # the paper's order: a peak off the mask's cell is lost
        out[_COLS * r + c] = row[c]
    return out
