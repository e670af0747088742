"""Section: classifier backends and model widths, latency against accuracy."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from deploy.bench.fmt import IMG_DIR, TIE_FRACTION, num, pct, pyplot, results_of, save_figure, table
from deploy.bench.section import Context, DefaultCheck, Results, Section

TITLE = "Run time against error: classifier backends and model widths"

ALL_BACKENDS = ("numba", "numpy", "onnxruntime", "torchscript", "torch")


@dataclass(frozen=True)
class ClassifierSizes:
    clf_calls: int  # back to back, per backend
    clf_paced_calls: int
    clf_eval_repeats: int  # of the default pad model's frame set
    clf_randomized_repeats: int  # 0: no domain-randomised set
    clf_backends_default: tuple[str, ...]  # compared on the shipped model
    clf_backends_others: tuple[str, ...]  # compared on the other widths' models
    pace_hz: float


SIZES = {
    "full": ClassifierSizes(
        clf_calls=5000,
        clf_paced_calls=600,
        clf_eval_repeats=4,
        clf_randomized_repeats=8,
        clf_backends_default=ALL_BACKENDS,
        clf_backends_others=("numba", "onnxruntime"),
        pace_hz=120.0,
    ),
    "quick": ClassifierSizes(
        clf_calls=1000,
        clf_paced_calls=150,
        clf_eval_repeats=1,
        clf_randomized_repeats=1,
        clf_backends_default=("numba", "numpy", "onnxruntime"),  # torch costs 10 s to load
        clf_backends_others=("numba",),
        pace_hz=120.0,
    ),
    "smallest": ClassifierSizes(
        clf_calls=50,
        clf_paced_calls=10,
        clf_eval_repeats=1,
        clf_randomized_repeats=0,
        clf_backends_default=("numba", "numpy", "onnxruntime"),
        clf_backends_others=(),
        pace_hz=500.0,
    ),
}


def measure(ctx: Context, sizes: ClassifierSizes) -> dict[str, Any]:
    from deploy.bench import classifier as cb
    from deploy.bench.fixtures import frame_set
    from deploy.bench.timing import limit_torch_threads

    eval_default = frame_set(sizes.clf_eval_repeats, seed=11)
    eval_rand = (
        cb.randomized_eval_set(sizes.clf_randomized_repeats)
        if sizes.clf_randomized_repeats > 0
        else None
    )
    out = cb.classifier_tradeoff(
        cb.find_models(ctx.models),
        list(sizes.clf_backends_default),
        list(sizes.clf_backends_others),
        eval_default,
        eval_rand,
        sizes.clf_calls,
        sizes.clf_paced_calls,
        1.0 / sizes.pace_hz,
    )
    limit_torch_threads()  # loading torch may have reset them
    return out


def default_checks(results: Results) -> list[DefaultCheck]:
    """classifier.backend and the model width against latency and accuracy measured."""
    d = results["defaults"]
    clf = results_of(results, "classifier")
    if clf is None:
        return []
    checks: list[DefaultCheck] = []
    # the node classifies a frame on a cold core: paced times decide when measured
    key = (
        "paced_median_us"
        if all("paced_median_us" in r for r in clf["rows"] if "median_us" in r)
        else "median_us"
    )
    shipped = [r for r in clf["rows"] if r["model"] == "shipped default" and "median_us" in r]
    exact = [r for r in shipped if r["agrees_with_first_backend"] == 1.0]
    if exact:
        fastest = min(exact, key=lambda r: r[key])
        default_row = next((r for r in exact if r["backend"] == d["backend"]), None)
        agrees = default_row is not None and (default_row[key] <= fastest[key] * (1 + TIE_FRACTION))
        checks.append(
            DefaultCheck(
                setting="classifier.backend",
                default=d["backend"]
                + (
                    " (first installed of the preference order)"
                    if d["backend_configured"] is None
                    else ""
                ),
                best=fastest["backend"],
                agrees=agrees,
                why=", ".join(
                    f"{r['backend']}: {num(r.get('paced_median_us'))} / "
                    f"{num(r.get('paced_p99_us'))} us paced, {num(r['median_us'])} / "
                    f"{num(r['p99_us'])} us back to back"
                    for r in exact
                )
                + " (median / p99 of predict_one, the node's call; shipped model, "
                f"identical predictions; decided by {key.replace('_us', '')})"
                + _backend_cpu_note(results),
            )
        )
    models = [r for r in clf["rows"] if "median_us" in r and r["backend"] == d["backend"]]
    if len({r["width"] for r in models}) > 1:
        acc_key = (
            "accuracy_randomized"
            if all(r.get("accuracy_randomized") is not None for r in models)
            else "accuracy_default_generator"
        )
        best_acc = max(r[acc_key] for r in models)
        good = [r for r in models if r[acc_key] >= best_acc - 0.005]
        choice = min(good, key=lambda r: r[key])
        checks.append(
            DefaultCheck(
                setting="model width (shipped model)",
                default=str(d["model_width"]),
                best=str(choice["width"]),
                agrees=choice["width"] == d["model_width"]
                or any(
                    r["width"] == d["model_width"] and r[key] <= choice[key] * (1 + TIE_FRACTION)
                    for r in good
                ),
                why="; ".join(
                    f"{r['model']} (w={r['width']}): {pct(r[acc_key], 2)}, "
                    f"{num(r[key])} us, worst robustness set "
                    f"{pct(r.get('report_worst_robustness'), 1)}"
                    for r in models
                )
                + f" ({acc_key.replace('_', ' ')}, backend {d['backend']}; best = the "
                "fastest within 0.5 points of the most accurate; robustness from each "
                "model's training report)",
            )
        )
    else:
        checks.append(
            DefaultCheck(
                setting="model width (shipped model)",
                default=str(d["model_width"]),
                best="not compared",
                agrees=None,
                why="no other width's model file was found (pass --models); "
                "no model is trained by the bench",
            )
        )
    return checks


def _backend_cpu_note(results: dict[str, Any]) -> str:
    """The other side of the backend choice: the robot node's CPU with each (Scale)."""
    scale = results_of(results, "scale")
    rows = [] if scale is None else scale.get("measured") or []
    at_120 = {
        r["backend"]: r["cpu_percent"]
        for r in rows
        if r.get("content") == "demo scene" and r["rate_hz"] == 120 and r["publish_rate_hz"] == 60
    }
    if len(at_120) < 2:
        return ""
    return (
        ". The robot node at 120 Hz (Scale) uses "
        + ", ".join(f"{num(v)} % of a core with {k}" for k, v in at_120.items())
        + ": latency per frame and CPU per second need not favour the same backend; "
        "latency decides while both are inside the CPU target"
    )


def markdown(results: Results) -> list[str]:
    s = results_of(results, "classifier")
    out = ["", f"## {TITLE}", ""]
    if s is None:
        return [*out, "Not run."]
    gap = s.get("paced_gap_s")
    out += [
        "Time: `predict_one`, the robot node's call (one frame through preallocated buffers, "
        "the softmax over seven Python floats), one thread; back to back, and paced with "
        + (
            "no pause (not run)"
            if gap is None
            else f"{1e3 * gap:.1f} ms of sleep before each "
            "call, as the node meets a frame on a cold core"
        )
        + ". Backends take turns call by call. "
        f"Accuracy: the pattern (both heads right) on "
        f"{s['eval_default_frames']:,} frames of the default pad model (seed "
        f"{s['eval_default_seed']}) and on "
        f"{num(s['eval_randomized_frames'])} domain-randomised frames drawn like the training "
        f"data from an unused seed ({s['eval_randomized_seed']}). Stimulus match: the "
        "predicted mask rendered with the node's defaults against the true pattern. No model "
        "is trained by the bench: the other widths are the perception engineer's width "
        "sweep (`python -m deploy.bench.perception_sweep --widths`, read from "
        "`runs/width-sweep` or `--models`), and the last two columns are copied from each "
        "model's own training report (its test split and the worst of its robustness sets, "
        "docs/perception.md).",
        "",
    ]
    rows = []
    for r in s["rows"]:
        if "error" in r:
            rows.append(
                [
                    r["model"],
                    str(r.get("width")),
                    num(r.get("parameters")),
                    r["backend"],
                    "unavailable",
                    "",
                    "",
                    "",
                    "",
                    "",
                    "",
                    "",
                    "",
                    "",
                ]
            )
            continue
        rows.append(
            [
                r["model"],
                str(r["width"]),
                num(r["parameters"]),
                r["backend"],
                num(r.get("paced_median_us")),
                num(r.get("paced_p99_us")),
                num(r["median_us"]),
                num(r["p99_us"]),
                pct(r["accuracy_default_generator"], 2),
                pct(r["accuracy_randomized"], 2),
                pct(r["stimulus_match"], 2),
                pct(r["agrees_with_first_backend"], 2),
                pct(r.get("report_test_accuracy"), 2),
                pct(r.get("report_worst_robustness"), 2),
            ]
        )
    out += table(
        [
            "model",
            "width",
            "parameters",
            "backend",
            "paced: median (us)",
            "p99 (us)",
            "back to back: median (us)",
            "p99 (us)",
            "accuracy, default pads",
            "accuracy, randomised",
            "stimulus match",
            "same predictions as first backend",
            "test accuracy (its training report)",
            "worst robustness set (its training report)",
        ],
        rows,
        "|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    )
    out += ["", f"![classifier]({IMG_DIR}/bench_classifier.png)"]
    return out


def figure(result: dict[str, Any], path: Path) -> Path:
    plt = pyplot()
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
    return save_figure(fig, path)


SECTION = Section(
    name="classifier",
    title=TITLE,
    sizes=SIZES,
    measure=measure,
    markdown=markdown,
    figure=figure,
    default_checks=default_checks,
)
