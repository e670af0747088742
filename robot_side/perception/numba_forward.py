"""The TiltNet forward pass compiled to one machine-code function (numba).

Why a fifth backend for a network of about 100 k multiply-adds: the robot
node classifies one frame per sensor period, and between two frames the core
runs other work, so every frame meets cold caches and branch predictors.
Then the cost of a forward pass is set by how much distinct code it runs, not
by its arithmetic: ONNX Runtime's session machinery costs about 300 us a
frame that way, NumPy's dozen calls about as much. Here the whole pass, from
the input features to both heads' logits, is a few kilobytes of straight
loops behind a single call.

Batch norm (eval mode) is folded into the convolutions in float64, then
everything is float32 with the summation order left to the compiler (fast
math without the non-finite assumptions), so logits agree with eager torch
to about 1e-5 (tests/perception). The first load compiles for about 2 s and
caches the machine code beside this file (or in the user's cache directory
when that is read-only); later loads take a fraction of a second.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from common.tactile.contract import CONTACT_FLOOR_N, FRAME_SHAPE, SATURATION_N
from robot_side.jit.cache import njit
from robot_side.perception.errors import ModelLoadError
from robot_side.perception.folding import block_diag, fold_batch_norm

#: reassociation (vectorised sums), contraction (FMA), no signed zeros, reciprocals;
#: not "nnan"/"ninf": a frame is finite by the time it is classified, but the
#: compiler must not be allowed to assume it
_FASTMATH = {"reassoc", "contract", "nsz", "arcp"}
_F0 = np.float32(0.0)
_NINTH = np.float32(1.0 / SATURATION_N)
_PEAK_FLOOR = np.float32(CONTACT_FLOOR_N)


@njit(fastmath=_FASTMATH)
def _dense(z, w, b, out, relu):  # pragma: no cover - compiled
    for o in range(w.shape[0]):
        acc = b[o]
        for k in range(w.shape[1]):
            acc += z[k] * w[o, k]
        if relu and acc < _F0:
            acc = _F0
        out[o] = acc


@njit(fastmath=_FASTMATH)
def _conv3x3(src, w, b, o, acc):  # pragma: no cover - compiled
    """Output channel ``o`` of a 3x3 convolution of zero-padded ``src`` into ``acc`` (10, 10)."""
    for i in range(10):
        for j in range(10):
            acc[i, j] = b[o]
    for c in range(w.shape[1]):
        for di in range(3):
            for dj in range(3):
                wv = w[o, c, di, dj]
                for i in range(10):
                    for j in range(10):
                        acc[i, j] += wv * src[c, i + di, j + dj]


@njit(fastmath=_FASTMATH)
def _forward_one(
    x, w1, b1, w2, b2, heads, biases, pad1, pad2, acc, scratch, out
):  # pragma: no cover
    """One ``FRAME_SHAPE`` frame -> 7 logits in ``out``; every buffer is preallocated.

    ``pad1`` (4, 12, 12) and ``pad2`` (c1, 12, 12) keep zero borders, so the
    3x3 convolutions run without bounds tests. ``heads``/``biases`` are the
    four merged head layers; ``scratch`` holds each layer's output.
    """
    c1 = w1.shape[0]
    c2 = w2.shape[0]
    peak = _PEAK_FLOOR
    for c in range(2):
        for i in range(10):
            for j in range(10):
                v = x[c, i, j]
                if v > peak:
                    peak = v
    inv_peak = np.float32(1.0) / peak
    # InputFeatures: (pad 0, pad 1) / 9 N, then (pad 0, pad 1) / peak
    for c in range(2):
        for i in range(10):
            for j in range(10):
                v = x[c, i, j]
                pad1[c, i + 1, j + 1] = v * _NINTH
                pad1[c + 2, i + 1, j + 1] = v * inv_peak
    for o in range(c1):
        _conv3x3(pad1, w1, b1, o, acc)
        for i in range(10):
            for j in range(10):
                v = acc[i, j]
                pad2[o, i + 1, j + 1] = v if v > _F0 else _F0
    h2 = scratch[0]
    for o in range(c2):
        _conv3x3(pad2, w2, b2, o, acc)
        for i in range(10):
            for j in range(10):
                v = acc[i, j]
                h2[o * 100 + i * 10 + j] = v if v > _F0 else _F0  # torch's flatten order
    n = len(heads)
    for k in range(n - 1):
        _dense(scratch[k], heads[k], biases[k], scratch[k + 1], True)
    _dense(scratch[n - 1], heads[n - 1], biases[n - 1], out, False)


@njit()
def _argmax_softmax(z, out, at):  # pragma: no cover - compiled
    """Class of ``z`` into ``out[0]`` (ties: the lowest, as NumPy), its softmax from ``at``."""
    top = 0
    for k in range(1, z.shape[0]):
        if z[k] > z[top]:
            top = k
    total = 0.0
    for k in range(z.shape[0]):
        e = np.exp(np.float64(z[k]) - np.float64(z[top]))
        out[at + k] = e
        total += e
    for k in range(z.shape[0]):
        out[at + k] /= total
    out[0] = top


@njit()
def classify_frame(
    x, w1, b1, w2, b2, heads, biases, pad1, pad2, acc, scratch, logits, n_angle, result
):  # pragma: no cover
    """``result``: angle, position, then both heads' probabilities (float64)."""
    _forward_one(x, w1, b1, w2, b2, heads, biases, pad1, pad2, acc, scratch, logits)
    _argmax_softmax(logits[:n_angle], result, 2)
    angle = result[0]
    _argmax_softmax(logits[n_angle:], result, 2 + n_angle)
    result[1] = result[0]
    result[0] = angle


@njit()
def _forward_batch(
    xs, w1, b1, w2, b2, heads, biases, pad1, pad2, acc, scratch, outs
):  # pragma: no cover
    for i in range(xs.shape[0]):
        _forward_one(xs[i], w1, b1, w2, b2, heads, biases, pad1, pad2, acc, scratch, outs[i])


class NumbaForward:
    """Logits of (N, 2, 10, 10) frames; ``one`` for a single frame through fixed buffers.

    Not thread-safe: the buffers are shared (TiltClassifier holds a lock).
    """

    def __init__(self, weights: dict[str, np.ndarray], meta: dict[str, Any]) -> None:
        try:
            w1, b1 = fold_batch_norm(
                weights["backbone.0.weight"], weights["backbone.0.bias"], weights, "backbone.1"
            )
            w2, b2 = fold_batch_norm(
                weights["backbone.3.weight"], weights["backbone.3.bias"], weights, "backbone.4"
            )
            heads = [
                np.concatenate([weights["angle_head.0.weight"], weights["position_head.0.weight"]])
            ]
            biases = [
                np.concatenate([weights["angle_head.0.bias"], weights["position_head.0.bias"]])
            ]
            for i in (3, 6, 9):
                a, p = weights[f"angle_head.{i}.weight"], weights[f"position_head.{i}.weight"]
                heads.append(block_diag(a, p))
                biases.append(
                    np.concatenate(
                        [weights[f"angle_head.{i}.bias"], weights[f"position_head.{i}.bias"]]
                    )
                )
            self.n_angle = weights["angle_head.9.weight"].shape[0]
        except KeyError as e:
            raise ModelLoadError(f"model weights lack {e}: not a TiltNet file") from None

        def f32(a: np.ndarray) -> np.ndarray:
            return np.ascontiguousarray(a, dtype=np.float32)

        self._weights = (f32(w1), f32(b1), f32(w2), f32(b2))
        # tuples of arrays: numba types them once, a list would be re-checked per call
        self._heads = tuple(f32(h) for h in heads)
        self._biases = tuple(f32(b) for b in biases)
        self._args = self.kernel_args()
        self._out = np.zeros(self.n_logits, np.float32)
        self._result = np.zeros(2 + self.n_logits, np.float64)
        # frames are copied in: one argument type, so nothing compiles on the hot path
        # (a read-only or strided array would be a new signature, a 2 s compile)
        self._x = np.zeros(FRAME_SHAPE, np.float32)
        # compile (or load the cached machine code) now, not on the first frame
        self.classify_one(np.zeros(FRAME_SHAPE, np.float32))

    @property
    def n_logits(self) -> int:
        return self._heads[-1].shape[0]

    def kernel_args(self) -> tuple[Any, ...]:
        """``_forward_one``'s arguments after the frame, before the output: the weights
        (shared; never written) and a fresh set of work buffers, for a caller that
        runs the pass in its own compiled code (``robot_side.node.compiled_step``)."""
        c1 = self._weights[0].shape[0]
        widths = [self._heads[0].shape[1]] + [h.shape[0] for h in self._heads[:-1]]
        return (
            *self._weights,
            self._heads,
            self._biases,
            np.zeros((4, 12, 12), np.float32),  # padded input features
            np.zeros((c1, 12, 12), np.float32),  # padded first layer
            np.zeros((10, 10), np.float32),  # one output channel's sums
            tuple(np.zeros(w, np.float32) for w in widths),  # each head layer's input
        )

    def classify_one(self, frame: np.ndarray) -> list[float]:
        """[angle, position, *angle probabilities, *position probabilities] of one frame."""
        result, x = self._result, self._x
        np.copyto(x, frame)
        classify_frame(x, *self._args, self._out, self.n_angle, result)
        return result.tolist()

    def one(self, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(4,) and (3,) logits of one float32 ``FRAME_SHAPE`` frame: views of reused buffers."""
        out, x = self._out, self._x
        np.copyto(x, frame)
        _forward_one(x, *self._args, out)
        return out[: self.n_angle], out[self.n_angle :]

    def __call__(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = np.require(x, np.float32, ("C", "W"))
        outs = np.empty((x.shape[0], self._out.shape[0]), np.float32)
        _forward_batch(x, *self._args, outs)
        return outs[:, : self.n_angle], outs[:, self.n_angle :]
