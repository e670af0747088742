"""Downsizing and rendering order: run time against the share of stimuli that match.

A stimulus matches when it presses exactly the true pattern's cells
(``common.tactile.matches_pattern``): that is what the operator feels.
Each downsizing method is crossed with both rendering orders and three
sources of the mask: the true pattern (the renderer alone), the
classifier's prediction (what the robot node does) and none (direct
rendering, the paper's baseline). The three methods are timed through
``render_contact``, the node's own path (since d31f386: the pad mean and
both weight matrices as one (9, 200) product, then mask and peak over nine
numbers in plain Python).

Two more variants, exact rewrites of the antialiased default:

- ``two_products``: the path before d31f386, contact map then ``Wy @ X @
  Wx.T`` then mask and peak in NumPy; kept here (not in the node's code) to
  show what the fusion saved, and as the tests' independent oracle;
- ``fused_masked``: only the rows of the (9, 200) matrix the mask keeps.
  Every pattern's mask has at most one cell per row, so masking first and
  then taking each row's peak is the masked cells themselves: 1 to 3 dot
  products of length 200 instead of nine.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import numpy as np

from common.stimulus import (
    METHODS,
    ORDERS,
    Method,
    downsizing_matrix,
    downsizing_weights,
    render_contact,
    render_stimulus,
    sanitize_frame,
)
from common.tactile import MASKS, MASKS_F32, SATURATION_N, matches_pattern
from deploy.bench.fixtures import FrameSet
from deploy.bench.timing import summarize_ns, time_interleaved

log = logging.getLogger(__name__)

#: variants beside the node's path (exact rewrites of the antialiased method)
EXTRA_VARIANTS = ("two_products", "fused_masked")


# The separable path: both pads' mean, then the two weight matrices one after the other.
# float32 copies: X is float32 and float64 buys nothing at 2e-7 N.
_SEPARABLE = {
    m: (
        downsizing_weights(m).astype(np.float32),
        np.ascontiguousarray(downsizing_weights(m).T, dtype=np.float32),
    )
    for m in METHODS
}


def contact_map(frame: np.ndarray) -> np.ndarray:
    """(2, 10, 10) frame -> (10, 10) mean of both pads."""
    return (frame[0] + frame[1]) * np.float32(0.5)


def downsize(cmap: np.ndarray, method: Method = "antialiased") -> np.ndarray:
    """(10, 10) -> (3, 3) float32: ``Wy @ X @ Wx.T``, clipped to [0, 9] N (cubic overshoot)."""
    wy, wxt = _SEPARABLE[method]
    out = wy @ cmap @ wxt
    np.clip(out, 0.0, SATURATION_N, out=out)
    return out


def peak_per_row(x: np.ndarray) -> np.ndarray:
    """Keep the largest cell of each row (ties: lowest column); zero the rest."""
    out = np.zeros_like(x)
    cols = np.argmax(x, axis=1)
    rows = np.arange(x.shape[0])
    out[rows, cols] = x[rows, cols]
    return out


def separable_stimulus(
    frame: np.ndarray, pattern: int | None, order: str, method: Method = "antialiased"
) -> np.ndarray:
    """The stimulus for a sanitized contact frame through the separable path."""
    small = downsize(contact_map(frame), method)
    if pattern is None:
        return peak_per_row(small)
    mask = MASKS_F32[pattern]
    return peak_per_row(small * mask) if order == "mask_then_peak" else peak_per_row(small) * mask


class FusedRenderer:
    """The fused variants of downsizing + masking; agree with render_stimulus to float32."""

    def __init__(self, method: Method = "antialiased") -> None:
        self.m = downsizing_matrix(method)
        # per pattern: the flat indices of its cells and their rows of the fused matrix
        self.cells = [np.flatnonzero(MASKS[p].ravel()) for p in range(len(MASKS))]
        self.rows = [np.ascontiguousarray(self.m[c]) for c in self.cells]

    def downsize(self, frame: np.ndarray) -> np.ndarray:
        out = (self.m @ frame.reshape(200)).reshape(3, 3)
        np.clip(out, 0.0, SATURATION_N, out=out)
        return out

    def masked(self, frame: np.ndarray, pattern: int) -> np.ndarray:
        """mask_then_peak for a mask with at most one cell per row: just those cells."""
        vals = self.rows[pattern] @ frame.reshape(200)
        np.clip(vals, 0.0, SATURATION_N, out=vals)
        out = np.zeros(9, np.float32)
        out[self.cells[pattern]] = vals
        return out.reshape(3, 3)

    def render(
        self, frame: np.ndarray, pattern: int | None, order: str, masked: bool
    ) -> np.ndarray:
        """A contact frame (already sanitized) -> stimulus."""
        if pattern is None:
            return peak_per_row(self.downsize(frame))
        if masked and order == "mask_then_peak":
            return self.masked(frame, pattern)
        small = self.downsize(frame)
        mask = MASKS_F32[pattern]
        if order == "peak_then_mask":
            return peak_per_row(small) * mask
        return peak_per_row(small * mask)


def _one_cell_per_row() -> bool:
    return bool((MASKS.sum(axis=2) <= 1).all())


def _render_fn(variant: str, fused: FusedRenderer) -> Callable[[np.ndarray, int | None, str], Any]:
    """The variant from a raw frame (sanitize and contact check first), for the match share."""
    if variant in METHODS:

        def fn(frame: np.ndarray, pattern: int | None, order: str) -> np.ndarray:
            return render_stimulus(frame, pattern, method=variant, order=order)

        return fn

    def other(frame: np.ndarray, pattern: int | None, order: str) -> np.ndarray:
        f = sanitize_frame(frame)
        if f.max() < 1.0:
            return np.zeros((3, 3), np.float32)
        if variant == "two_products":
            return separable_stimulus(f, pattern, order)
        return fused.render(f, pattern, order, masked=True)

    return other


def _timed_core(
    variant: str, fused: FusedRenderer, frames: np.ndarray, patterns: np.ndarray, order: str
) -> Callable[[int], Any]:
    """Downsizing + mask only (the frame is already sanitized and in contact)."""
    n = len(frames)
    if variant in METHODS:

        def fn(i: int) -> Any:
            return render_contact(frames[i % n], int(patterns[i % n]), method=variant, order=order)

        return fn
    if variant == "two_products":
        return lambda i: separable_stimulus(frames[i % n], int(patterns[i % n]), order)
    return lambda i: fused.render(frames[i % n], int(patterns[i % n]), order, masked=True)


def downsizing_tradeoff(
    fs: FrameSet, predicted: np.ndarray | None, time_calls_n: int
) -> dict[str, Any]:
    """Match share and time for every variant x order x mask source."""
    if not _one_cell_per_row():
        raise RuntimeError("a mask has two cells in one row: fused_masked would be wrong")
    fused = FusedRenderer("antialiased")
    variants = (*METHODS, *EXTRA_VARIANTS)
    sanitized = np.stack([sanitize_frame(f) for f in fs.frames])
    contact = sanitized.reshape(len(fs), -1).max(axis=1) >= 1.0
    sources: dict[str, np.ndarray | None] = {"true": fs.pattern, "none": None}
    if predicted is not None:
        sources["predicted"] = predicted
    combos = [
        (variant, order)
        for variant in variants
        # masking only the kept cells is possible only when the mask comes first
        for order in (("mask_then_peak",) if variant == "fused_masked" else ORDERS)
    ]
    times = time_interleaved(
        [_timed_core(v, fused, sanitized, fs.pattern, o) for v, o in combos],
        time_calls_n,
        warmup=200,
    )
    rows: list[dict[str, Any]] = []
    direct: dict[str, float] = {}
    for (variant, order), samples in zip(combos, times, strict=True):
        timing = summarize_ns(samples)
        render = _render_fn(variant, fused)
        row: dict[str, Any] = {
            "variant": variant,
            "order": order,
            "median_us": timing.median_us,
            "p99_us": timing.p99_us,
        }
        for source, pats in sources.items():
            if source == "none" and variant in direct:
                row["match_none"] = direct[variant]  # direct rendering has no order
                continue
            ok = 0
            for k in range(len(fs)):
                pat = None if pats is None else int(pats[k])
                ok += matches_pattern(render(fs.frames[k], pat, order), int(fs.pattern[k]))
            row[f"match_{source}"] = ok / len(fs)
            if source == "none":
                direct[variant] = row["match_none"]
        rows.append(row)
    agreement = _fused_agreement(fused, sanitized[contact], fs.pattern[contact])
    by_pattern = _per_pattern(fs, "antialiased")
    return {
        "frames": len(fs),
        "frames_in_contact": int(contact.sum()),
        "seed": fs.seed,
        "rows": rows,
        "fused_agreement": agreement,
        "per_pattern_antialiased_true": by_pattern,
    }


def _fused_agreement(
    fused: FusedRenderer, frames: np.ndarray, patterns: np.ndarray
) -> dict[str, Any]:
    """How far the fused variants are from the two-matrix reference, in newtons."""
    worst = 0.0
    worst_masked = 0.0
    same_support = 0
    for k, f in enumerate(frames):
        ref = downsize(contact_map(f), "antialiased")
        worst = max(worst, float(np.abs(fused.downsize(f) - ref).max()))
        p = int(patterns[k])
        ref_st = peak_per_row(ref * MASKS_F32[p])
        got = fused.masked(f, p)
        worst_masked = max(worst_masked, float(np.abs(got - ref_st).max()))
        same_support += bool(np.array_equal(got > 0, ref_st > 0))
    return {
        "max_abs_diff_fused_n": worst,
        "max_abs_diff_fused_masked_n": worst_masked,
        "same_cells_share": same_support / max(1, len(frames)),
        "frames": len(frames),
    }


def _per_pattern(fs: FrameSet, method: str) -> dict[str, dict[str, float]]:
    """Match share per pattern with the true mask: where the paper's order loses."""
    out: dict[str, dict[str, float]] = {}
    for p in range(len(MASKS)):
        idx = np.flatnonzero(fs.pattern == p)
        out[str(p)] = {
            order: float(
                np.mean(
                    [
                        matches_pattern(
                            render_stimulus(fs.frames[k], p, method=method, order=order), p
                        )
                        for k in idx
                    ]
                )
            )
            for order in ORDERS
        }
    return out
