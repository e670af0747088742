"""Downsizing and rendering order: run time against the share of stimuli that match.

A stimulus matches when it presses exactly the true pattern's cells
(``common.tactile.contract.matches_pattern``): that is what the operator feels.
Each downsizing method is crossed with both rendering orders and three
sources of the mask: the true pattern (the renderer alone), the
classifier's prediction (what the robot node does) and none (direct
rendering, the paper's baseline). The three methods are timed through
``render_contact``, the node's own path (the pad mean and
both weight matrices as one (9, 200) product, then mask and peak over nine
numbers in plain Python).

Two more variants, exact rewrites of the antialiased default:

- ``two_products``: the node's earlier path, contact map then ``Wy @ X @
  Wx.T`` then mask and peak in NumPy; kept here (not in the node's code) to
  show what the fusion saved, and as the tests' independent oracle;
- ``fused_masked``: only the rows of the (9, 200) matrix the mask keeps.
  Every pattern's mask has at most one cell per row, so masking first and
  then taking each row's peak is the masked cells themselves: 1 to 3 dot
  products of length 200 instead of nine.

As a bench section: downsizing and rendering order, run time against the stimulus match.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from common.tactile.contract import MASKS, MASKS_F32, SATURATION_N, matches_pattern
from common.tactile.stimulus import (
    METHODS,
    ORDERS,
    Method,
    downsizing_matrix,
    downsizing_weights,
    render_contact,
    render_stimulus,
    sanitize_frame,
)
from harness.bench.fixtures import FrameSet
from harness.bench.fmt import (
    IMG_DIR,
    TIE_FRACTION,
    num,
    pct,
    pyplot,
    results_of,
    save_figure,
    sci,
    table,
)
from harness.bench.section import Context, DefaultCheck, Results, Section
from harness.bench.timing import summarize_ns, time_interleaved

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
    """``FRAME_SHAPE`` frame -> (10, 10) mean of both pads."""
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


TITLE = "Run time against error: downsizing and rendering order"


@dataclass(frozen=True)
class DownsizingSizes:
    ds_repeats: int  # of the 12 x 31 frame set
    ds_calls: int


SIZES = {
    "full": DownsizingSizes(ds_repeats=8, ds_calls=20000),
    "quick": DownsizingSizes(ds_repeats=1, ds_calls=1000),
    "smallest": DownsizingSizes(ds_repeats=1, ds_calls=100),
}


def measure(ctx: Context, sizes: DownsizingSizes) -> dict[str, Any]:
    from common.tactile.contract import patterns_of
    from harness.bench.fixtures import frame_set

    fs = frame_set(sizes.ds_repeats, seed=0)
    a, p = ctx.classifier.predict(fs.frames)
    return downsizing_tradeoff(fs, patterns_of(a, p), sizes.ds_calls)


def default_checks(results: Results) -> list[DefaultCheck]:
    """render.order and render.method against the match and the time measured."""
    d = results["defaults"]
    ds = results_of(results, "downsizing")
    if ds is None:
        return []
    checks: list[DefaultCheck] = []
    src = "match_predicted" if any("match_predicted" in r for r in ds["rows"]) else "match_true"
    code_rows = [r for r in ds["rows"] if r["variant"] in ("antialiased", "plain", "area")]
    # order: at the default method
    by_order = {r["order"]: r[src] for r in code_rows if r["variant"] == d["method"]}
    best_order = max(by_order, key=lambda k: by_order[k])
    tied_orders = [k for k, v in by_order.items() if v == by_order[best_order]]
    checks.append(
        DefaultCheck(
            setting="render.order",
            default=d["order"],
            best=best_order,
            agrees=d["order"] in tied_orders,
            why=", ".join(f"{k}: {pct(v)}" for k, v in by_order.items())
            + f" of stimuli match ({src.replace('match_', '')} mask, {d['method']})",
        )
    )
    at_order = [r for r in code_rows if r["order"] == d["order"]]
    best_match = max(r[src] for r in at_order)
    tied = [r for r in at_order if r[src] == best_match]
    fastest = min(tied, key=lambda r: r["median_us"])
    default_row = next(r for r in at_order if r["variant"] == d["method"])
    time_tie = default_row["median_us"] <= fastest["median_us"] * (1 + TIE_FRACTION)
    agrees = default_row in tied and time_tie
    why = (
        ", ".join(f"{r['variant']}: {pct(r[src])} in {num(r['median_us'])} us" for r in at_order)
        + f" ({d['order']}, through the node's render_contact). The three methods are "
        "the same (9 x 200) product with different weights, so their times differ only "
        "by noise."
    )
    direct = {r["variant"]: r.get("match_none") for r in at_order}
    if direct and max(direct.values() or [0]) > (direct.get(d["method"]) or 0):
        best_direct = max(direct, key=lambda k: direct[k] or 0)
        why += (
            f" In direct mode (no mask) {best_direct} matches more often "
            f"({pct(direct[best_direct])} against {pct(direct.get(d['method']))}): "
            "relevant only to the paper's baseline."
        )
    fused = [r for r in ds["rows"] if r["variant"] == "fused_masked"]
    if fused:
        why += (
            f" The exact rewrite fused_masked (not in the code) takes "
            f"{num(fused[0]['median_us'])} us for the same output."
        )
    checks.append(
        DefaultCheck(
            setting="render.method",
            default=d["method"],
            best=d["method"] if agrees else fastest["variant"],
            agrees=agrees or default_row in tied,
            why=why,
        )
    )
    return checks


def markdown(results: Results) -> list[str]:
    s = results_of(results, "downsizing")
    out = ["", f"## {TITLE}", ""]
    if s is None:
        return [*out, "Not run."]
    out += [
        f"{s['frames']:,} frames (12 patterns x 31 grip levels x {s['frames'] // 372}, "
        f"seed {s['seed']}, default pad model; {s['frames_in_contact']:,} in contact). "
        "Time: downsizing + masking of one frame already sanitized (median and p99, us, "
        "back to back, the variants taking turns call by call); antialiased, plain and area "
        "through the node's `render_contact`. "
        "Match: the share of stimuli pressing exactly the true pattern's cells "
        "(`common.tactile.contract.matches_pattern`) with the true pattern's mask, with the "
        "classifier's predicted pattern (the node's path), and with no mask (direct).",
        "",
    ]
    out += table(
        [
            "variant",
            "order",
            "median (us)",
            "p99 (us)",
            "match, true mask",
            "match, predicted mask",
            "match, direct",
        ],
        [
            [
                r["variant"],
                r["order"],
                num(r["median_us"]),
                num(r["p99_us"]),
                pct(r.get("match_true")),
                pct(r.get("match_predicted")),
                pct(r.get("match_none")),
            ]
            for r in s["rows"]
        ],
        "|---|---|---:|---:|---:|---:|---:|",
    )
    a = s["fused_agreement"]
    aa = {r["order"]: r.get("match_true") for r in s["rows"] if r["variant"] == "antialiased"}
    out += [
        "",
        "`two_products` is the node's earlier path (contact map, then `Wy @ X @ "
        "Wx.T`, then mask and peak in NumPy); the node now folds the pad mean and both "
        "weight matrices into one (9 x 200) product. `fused_masked` keeps only the mask's "
        "rows of that matrix (every mask has at most one cell per row, so masking first and "
        "taking the peak is those cells). Against the two-product reference over "
        f"{a['frames']:,} frames: largest difference {sci(a['max_abs_diff_fused_n'])} N "
        f"(one product) and {sci(a['max_abs_diff_fused_masked_n'])} N (fused_masked), same "
        f"cells pressed in {pct(a['same_cells_share'])}.",
        "",
        "Where the paper's order loses (true mask, antialiased), per pattern:",
        "",
    ]
    from common.tactile.contract import pattern_name

    pp = s["per_pattern_antialiased_true"]
    out += table(
        ["pattern", "peak_then_mask", "mask_then_peak"],
        [
            [f"{k}: {pattern_name(int(k))}", pct(v["peak_then_mask"]), pct(v["mask_then_peak"])]
            for k, v in pp.items()
        ],
        "|---|---:|---:|",
    )
    out += [
        "",
        "docs/tactile.md reports 79.4 % (the paper's order) against 100.0 % (masked first) for "
        "12 x 31 x 4 frames, antialiased, true mask; this run measures "
        f"{pct(aa['peak_then_mask'])} against {pct(aa['mask_then_peak'])} on "
        f"{s['frames']:,} frames.",
        "",
        f"![downsizing]({IMG_DIR}/bench_downsizing.png)",
    ]
    return out


def figure(result: dict[str, Any], path: Path) -> Path:
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.4), sharey=True)
    markers = {"peak_then_mask": "o", "mask_then_peak": "s"}
    variants = list(dict.fromkeys(r["variant"] for r in result["rows"]))
    colors = {v: f"C{k}" for k, v in enumerate(variants)}
    for ax, source, title in (
        (axes[0], "match_true", "true pattern's mask"),
        (axes[1], "match_predicted", "classifier's mask (the node)"),
    ):
        for row in result["rows"]:
            if source not in row:
                continue
            ax.scatter(
                row["median_us"],
                100 * row[source],
                marker=markers[row["order"]],
                color=colors[row["variant"]],
                s=60,
                alpha=0.8,
            )
        ax.set_title(title)
        ax.set_xlabel("median time per frame (us, one core)")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("stimuli matching the true pattern (%)")
    handles = [
        plt.Line2D([], [], color=colors[v], marker="o", ls="", label=v) for v in variants
    ] + [
        plt.Line2D([], [], color="grey", marker=m, ls="", label=o.replace("_", " "))
        for o, m in markers.items()
    ]
    axes[1].legend(handles=handles, fontsize=8, loc="center right")
    fig.suptitle("downsizing + masking: run time against the stimulus match")
    return save_figure(fig, path)


SECTION = Section(
    name="downsizing",
    title=TITLE,
    sizes=SIZES,
    measure=measure,
    markdown=markdown,
    figure=figure,
    default_checks=default_checks,
)
