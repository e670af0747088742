"""The TiltNet forward pass in plain NumPy: the ``numpy`` backend, and the reference of speed.

Batch norm folded into the convolutions, convolutions as one gather and
one matrix product, both heads merged into block-diagonal matrices
(``folding``). No dependency beyond NumPy.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from common.tactile.contract import CONTACT_FLOOR_N, SATURATION_N
from robot_side.perception.errors import ModelLoadError
from robot_side.perception.folding import block_diag, fold_batch_norm

#: a batch's (angle logits, position logits)
Logits = tuple[np.ndarray, np.ndarray]


def _conv_gather_index(channels: int, channels_last: bool) -> np.ndarray:
    """Indices into a zero-padded (12 x 12) input that lay out every 3x3 patch as a row.

    Rows are output pixels (r * 10 + c); columns follow the weight layout the
    matching matrix is built with: (channel, ky, kx) for channels-first input,
    (ky, kx, channel) for channels-last.
    """
    r, c = np.divmod(np.arange(100), 10)
    ky, kx = np.divmod(np.arange(9), 3)
    pix = (r[:, None] + ky[None, :]) * 12 + (c[:, None] + kx[None, :])  # (100, 9)
    ch = np.arange(channels)
    if channels_last:
        idx = pix[:, :, None] * channels + ch[None, None, :]  # (100, 9, C)
    else:
        idx = ch[None, :, None] * 144 + pix[:, None, :]  # (100, C, 9)
    return np.ascontiguousarray(idx.reshape(100, -1)).astype(np.intp)


def _with_bias_row(w: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(K, M) weights and (M,) bias as one (K + 1, M) matrix for inputs ending in a 1."""
    return np.ascontiguousarray(np.vstack([w, b[None, :]]), dtype=np.float32)


class NumpyForward:
    """The TiltNet forward pass in NumPy, exact to float32 rounding.

    Layout: pixels as rows, channels as columns, so both convolutions and all
    linear layers are single matrix products. Batch norm (eval mode) is folded
    into the convolutions in float64 before rounding to float32. Every input
    buffer ends in a constant 1 and every matrix in a bias row, so a layer is
    one product and one in-place ReLU: at batch 1 the cost is per call, not
    per multiply.
    """

    def __init__(self, weights: dict[str, np.ndarray], meta: dict[str, Any]) -> None:
        try:
            self._build(weights)
        except KeyError as e:
            raise ModelLoadError(f"model weights lack {e}: not a TiltNet file") from None
        self._buffers: dict[int, dict[str, Any]] = {}

    def _build(self, w: dict[str, np.ndarray]) -> None:
        w1, b1 = fold_batch_norm(w["backbone.0.weight"], w["backbone.0.bias"], w, "backbone.1")
        w2, b2 = fold_batch_norm(w["backbone.3.weight"], w["backbone.3.bias"], w, "backbone.4")
        self.c1, self.c2 = c1, c2 = w1.shape[0], w2.shape[0]
        # conv1 reads the input channels-first; its 4 feature channels are
        # (pad 0, pad 1) / 9 N, then (pad 0, pad 1) / peak, as InputFeatures.
        self.w1 = _with_bias_row(w1.reshape(c1, 4 * 9).T, b1)
        self.w2 = _with_bias_row(w2.transpose(2, 3, 1, 0).reshape(9 * c1, c2), b2)
        self.idx1 = _conv_gather_index(2, channels_last=False)
        # the extra column points at the constant 1 after the padded input
        idx2 = _conv_gather_index(c1, channels_last=True)
        self.idx2 = np.hstack([idx2, np.full((100, 1), 144 * c1, dtype=np.intp)])
        # Pixels by channel back to the (channel, row, column) order torch flattens.
        heads_in = []
        for head in ("angle_head", "position_head"):
            first = w[f"{head}.0.weight"]
            first = first.reshape(first.shape[0], c2, 10, 10).transpose(0, 2, 3, 1)
            heads_in.append(first.reshape(first.shape[0], -1))
        bias = np.concatenate([w["angle_head.0.bias"], w["position_head.0.bias"]])
        self.fc = [_with_bias_row(np.concatenate(heads_in).T, bias)]
        for i in (3, 6, 9):
            a_w, p_w = w[f"angle_head.{i}.weight"], w[f"position_head.{i}.weight"]
            bias = np.concatenate([w[f"angle_head.{i}.bias"], w[f"position_head.{i}.bias"]])
            self.fc.append(_with_bias_row(block_diag(a_w.T, p_w.T), bias))
        self.n_angle = w["angle_head.9.weight"].shape[0]

    def _buf(self, n: int) -> dict[str, Any]:
        buf = self._buffers.get(n)
        if buf is not None:
            return buf
        f32, c1, c2 = np.float32, self.c1, self.c2
        cols1 = np.zeros((n, 100, 37), f32)
        cols1[:, :, 36] = 1.0
        pad2 = np.zeros((n, 144 * c1 + 1), f32)
        pad2[:, -1] = 1.0
        h2 = np.ones((n, 100 * c2 + 1), f32)
        zs = []
        for wt in self.fc[:-1]:
            zs.append(np.ones((n, wt.shape[1] + 1), f32))
        buf = {
            "pad1": np.zeros((n, 2, 12, 12), f32),
            "cols1": cols1,
            "raw": cols1[:, :, :18],
            "scaled": cols1[:, :, 18:36],
            "h1": np.empty((n, 100, c1), f32),
            "pad2": pad2,
            "pad2_in": pad2[:, : 144 * c1].reshape(n, 12, 12, c1)[:, 1:11, 1:11, :],
            "cols2": np.empty((n, 100, 9 * c1 + 1), f32),
            "h2": h2,
            "h2_out": h2[:, : 100 * c2].reshape(n, 100, c2),
            "zs": zs,
            "zs_out": [z[:, :-1] for z in zs],
            "logits": np.empty((n, self.fc[-1].shape[1]), f32),
        }
        if n == 1:  # only the hot path keeps its buffers
            self._buffers[n] = buf
        return buf

    def __call__(self, x: np.ndarray) -> Logits:
        n = x.shape[0]
        b = self._buf(n)
        pad1, raw, scaled = b["pad1"], b["raw"], b["scaled"]
        pad1[:, :, 1:11, 1:11] = x
        np.take(pad1.reshape(n, -1), self.idx1, axis=1, out=raw)  # (n, 100, 18)
        # the peak-normalised copy first, then the raw columns scaled in place
        if n == 1:
            np.divide(raw, max(float(x.max()), CONTACT_FLOOR_N), out=scaled)
        else:
            peak = np.maximum(x.reshape(n, -1).max(axis=1), CONTACT_FLOOR_N).reshape(n, 1, 1)
            np.divide(raw, peak, out=scaled)
        np.multiply(raw, np.float32(1.0 / SATURATION_N), out=raw)
        h1 = b["h1"]
        np.matmul(b["cols1"], self.w1, out=h1)
        np.maximum(h1.reshape(n, 10, 10, self.c1), 0.0, out=b["pad2_in"])
        cols2 = b["cols2"]
        np.take(b["pad2"], self.idx2, axis=1, out=cols2)
        h2_out = b["h2_out"]
        np.matmul(cols2, self.w2, out=h2_out)
        np.maximum(h2_out, 0.0, out=h2_out)
        z = b["h2"]
        for wt, zn, zo in zip(self.fc[:-1], b["zs"], b["zs_out"], strict=True):
            np.matmul(z, wt, out=zo)
            np.maximum(zo, 0.0, out=zo)
            z = zn
        logits = b["logits"]
        np.matmul(z, self.fc[-1], out=logits)
        return logits[:, : self.n_angle], logits[:, self.n_angle :]
