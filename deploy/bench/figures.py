"""One PNG per trade-off curve (matplotlib, Agg: no display needed)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def downsizing(result: dict[str, Any], path: Path) -> Path:
    plt = _plt()
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
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def classifier(result: dict[str, Any], path: Path) -> Path:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 4.6))
    rows = [r for r in result["rows"] if "median_us" in r]
    backends = list(dict.fromkeys(r["backend"] for r in rows))
    widths = sorted({r["width"] for r in rows})
    colors = {b: f"C{k}" for k, b in enumerate(backends)}
    shapes = dict(zip(widths, "v^osDP*", strict=False))
    for r in rows:
        acc = r.get("accuracy_randomized") or r["accuracy_default_generator"]
        # filled: paced (a cold core, the node's case); hollow: back to back
        for median, p99, face in (
            (r.get("paced_median_us"), r.get("paced_p99_us"), colors[r["backend"]]),
            (r["median_us"], r["p99_us"], "none"),
        ):
            if median is None:
                continue
            ax.errorbar(
                median,
                100 * acc,
                xerr=[[0], [max(0.0, p99 - median)]],
                fmt=shapes[r["width"]],
                color=colors[r["backend"]],
                mfc=face,
                capsize=3,
                alpha=0.8,
                ms=7,
            )
    handles = [plt.Line2D([], [], color=colors[b], marker="o", ls="", label=b) for b in backends]
    handles += [
        plt.Line2D([], [], color="grey", marker=shapes[w], ls="", label=f"width {w:g}")
        for w in widths
    ]
    handles += [
        plt.Line2D([], [], color="grey", marker="o", ls="", label="paced (cold core)"),
        plt.Line2D([], [], color="grey", marker="o", mfc="none", ls="", label="back to back"),
    ]
    ax.legend(handles=handles, fontsize=8, loc="lower right")
    ax.set_xscale("log")
    ax.set_xlabel("predict_one latency, median (bar to p99), us, one core")
    ax.set_ylabel("pattern accuracy (%), randomised held-out set")
    ax.set_title("classifier: latency against accuracy")
    ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def ik(result: dict[str, Any], path: Path) -> Path:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 4.6))
    sets = (
        ("operational", "o", "contact points"),
        ("grid", "s", "workspace grid"),
        ("shell", "^", "edge shell"),
        ("grid_and_shell_sample", "D", "grid + shell sample"),
    )
    colors = {m["key"]: f"C{k}" for k, m in enumerate(result["methods"])}
    for m in result["methods"]:
        t = m["time_3"]["median_us"]
        for key, marker, _ in sets:
            if key in m and m[key]["max_mm"] is not None:
                ax.scatter(
                    t,
                    max(m[key]["max_mm"], 1e-16),
                    marker=marker,
                    s=55,
                    color=colors[m["key"]],
                    alpha=0.85,
                )
    handles = [
        plt.Line2D([], [], color=colors[m["key"]], marker="o", ls="", label=m["key"])
        for m in result["methods"]
    ] + [plt.Line2D([], [], color="grey", marker=mk, ls="", label=lb) for _, mk, lb in sets]
    ax.legend(handles=handles, fontsize=8, loc="center right")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("time for three linkages, median (us, one core)")
    ax.set_ylabel("largest round-trip error |FK(IK(p)) - p| (mm)")
    ax.set_title("IK: time against round-trip error")
    ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def skipping(result: dict[str, Any], path: Path) -> Path:
    plt = _plt()
    rows = [r for r in result["rows"] if r["kind"] != "published"]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    names = [r["kind"].replace("_", " ") for r in rows]
    axes[0].barh(names, [r["cpu_saved_us_per_s"] / 1e3 for r in rows])
    axes[0].set_xlabel("CPU saved (ms per second of scene)")
    axes[0].set_title(f"work saved in the {result['scene']} scene")
    diffs = [r["max_servo_counts_diff"] for r in rows]
    axes[1].barh(names, diffs, color=["#c44e52" if d else "#55a868" for d in diffs])
    for y, (d, r) in enumerate(zip(diffs, rows, strict=True)):
        axes[1].annotate(
            f" {d} counts, {r['max_abs_diff_n']:.3f} N",
            (max(d, 0), y),
            va="center",
            fontsize=8,
        )
    axes[1].set_xscale("symlog", linthresh=1)
    axes[1].set_xlabel("largest servo goal difference (counts; 1 count = 0.088 deg)")
    axes[1].set_title("error it costs")
    for ax in axes:
        ax.grid(alpha=0.3, axis="x")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def scale(result: dict[str, Any], path: Path) -> Path:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    measured = [
        r for r in result.get("measured", []) if r.get("content", "demo scene") == "demo scene"
    ]
    modelled = result["modelled"]
    for label, rows, style in (
        (
            "measured, 60 Hz render cap",
            [
                r
                for r in measured
                if r["publish_rate_hz"] < r["rate_hz"] and r["backend"] == "default"
            ],
            "o-",
        ),
        (
            "measured, every frame rendered",
            [r for r in measured if r["publish_rate_hz"] >= r["rate_hz"]],
            "s-",
        ),
        ("model, 60 Hz render cap", [r for r in modelled if r["capped"]], "o--"),
        ("model, every frame rendered", [r for r in modelled if not r["capped"]], "s--"),
    ):
        if not rows:
            continue
        seen: dict[float, float] = {}
        for r in rows:
            seen.setdefault(r["rate_hz"], r["cpu_percent"])
        xs = sorted(seen)
        ax.plot(xs, [seen[x] for x in xs], style, label=label)
    ax.axhline(10, color="grey", lw=0.8, ls=":")
    ax.annotate(
        "10 % budget at 120 Hz", (120, 10), fontsize=8, xytext=(4, 4), textcoords="offset points"
    )
    ax.set_xlabel("frame rate (Hz)")
    ax.set_ylabel("robot node CPU (% of one core)")
    ax.set_title("robot node cost against frame rate")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def stages(result: dict[str, Any], path: Path) -> Path:
    plt = _plt()
    names = list(result["stages"])
    paced = (result.get("paced") or {}).get("stages", {})
    series = [
        ("back to back, median", [result["stages"][n]["median_us"] for n in names], "#4c72b0"),
    ]
    if paced:
        rate = result["paced"]["pace_hz"]
        series.append(
            (
                f"paced {rate:g} Hz, median",
                [paced.get(n, {}).get("median_us", float("nan")) for n in names],
                "#dd8452",
            )
        )
        series.append(
            (
                f"paced {rate:g} Hz, p99",
                [paced.get(n, {}).get("p99_us", float("nan")) for n in names],
                "#f2c8a8",
            )
        )
    fig, ax = plt.subplots(figsize=(8.5, 5))
    h = 0.8 / len(series)
    for k, (label, values, color) in enumerate(series):
        ax.barh(
            [i - 0.4 + h * (k + 0.5) for i in range(len(names))],
            values,
            height=h,
            label=label,
            color=color,
        )
    ax.set_yticks(list(range(len(names))), names)
    ax.invert_yaxis()
    ax.set_xscale("log")
    ax.set_xlabel("microseconds (one core)")
    ax.set_title("latency budget per stage")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, axis="x", which="both")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
