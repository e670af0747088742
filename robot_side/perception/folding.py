"""TiltNet's weights rearranged for the hand-written forward passes (NumPy, numba).

Both fold each eval-mode batch norm into the convolution before it and merge
the two heads' layers into one matrix per layer; keeping these steps here
lets ``inference`` and ``numba_forward`` share them without importing each
other.
"""

from __future__ import annotations

import numpy as np

#: ``nn.BatchNorm2d``'s default epsilon, which TiltNet trains with
BN_EPS = 1e-5


def fold_batch_norm(
    w: np.ndarray, b: np.ndarray, weights: dict[str, np.ndarray], prefix: str
) -> tuple[np.ndarray, np.ndarray]:
    """Conv weights and bias with the batch norm at ``prefix`` folded in, in float64.

    Folding in float64 before the caller rounds to float32 keeps the logits
    within 1e-5 of eager torch.
    """
    gamma = weights[f"{prefix}.weight"].astype(np.float64)
    beta = weights[f"{prefix}.bias"].astype(np.float64)
    mean = weights[f"{prefix}.running_mean"].astype(np.float64)
    var = weights[f"{prefix}.running_var"].astype(np.float64)
    scale = gamma / np.sqrt(var + BN_EPS)
    return w.astype(np.float64) * scale[:, None, None, None], (b - mean) * scale + beta


def block_diag(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a`` and ``b`` on the diagonal of one float64 matrix: two heads' layers as one."""
    out = np.zeros((a.shape[0] + b.shape[0], a.shape[1] + b.shape[1]), dtype=np.float64)
    out[: a.shape[0], : a.shape[1]] = a
    out[a.shape[0] :, a.shape[1] :] = b
    return out
