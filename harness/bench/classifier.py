"""Classifier: backends and model widths, batch-1 latency against accuracy.

No model is trained here (two cores are shared): the shipped model and any
other model files found (``--models``, e.g. the perception engineer's width
sweep in runs/width-sweep) are measured as they are. Accuracy is on seeded
frames none of them were trained on: the default pad model over every
pattern and grip level, and a domain-randomised set drawn like the training
data but from another seed. The stimulus match share is the end result:
the predicted pattern's mask, rendered with the node's defaults, against
the true pattern.

As a bench section: classifier backends and model widths, latency against accuracy.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from common.tactile.contract import matches_pattern, patterns_of
from common.tactile.stimulus import render_stimulus
from harness.bench.fixtures import FrameSet
from harness.bench.fmt import (
    IMG_DIR,
    TIE_FRACTION,
    num,
    pct,
    pyplot,
    results_of,
    save_figure,
    table,
)
from harness.bench.section import Context, DefaultCheck, Results, Section
from harness.bench.timing import summarize_ns, time_interleaved
from robot_side.node.config import RobotConfig
from robot_side.perception import BACKENDS, DEFAULT_MODEL, load_classifier
from robot_side.perception.weights import read_weights

log = logging.getLogger(__name__)

#: the domain-randomised evaluation set's seed: not any training seed in the project
RANDOMIZED_EVAL_SEED = 8_808


def find_models(dirs: list[Path]) -> list[Path]:
    """The shipped model first, then every other model file in ``dirs``."""
    out = [DEFAULT_MODEL]
    for d in dirs:
        if d.is_file() and d.suffix == ".npz":
            out.append(d)
        elif d.is_dir():
            out.extend(sorted(d.glob("*.npz")))
    seen: set[Path] = set()
    unique = []
    for p in out:
        r = p.resolve()
        if r not in seen:
            seen.add(r)
            unique.append(p)
    return unique


def _describe(path: Path) -> dict[str, Any]:
    """The model's size, and the accuracies its own training report gives, if beside it."""
    _, meta = read_weights(path)
    out: dict[str, Any] = {
        "model": "shipped default" if path.resolve() == DEFAULT_MODEL.resolve() else path.name,
        "path": str(path),
        "width": meta.get("model", {}).get("width"),
        "parameters": meta.get("parameters"),
        "report_test_accuracy": None,
        "report_worst_robustness": None,
    }
    report = path.with_suffix(".report.json")
    if report.is_file():
        try:
            r = json.loads(report.read_text())
            out["report_test_accuracy"] = r["test"]["both_accuracy"]
            rob = r.get("robustness", {})
            if rob:
                out["report_worst_robustness"] = min(v["both_accuracy"] for v in rob.values())
        except (OSError, ValueError, KeyError, TypeError) as e:
            log.warning("cannot read %s: %s", report, e)
    return out


def randomized_eval_set(repeats: int) -> FrameSet:
    """Frames drawn like the training data (randomised sensors), from an unused seed."""
    from robot_side.perception import dataset as ds

    data = ds.generate(ds.DatasetConfig(repeats=repeats, seed=RANDOMIZED_EVAL_SEED))
    return FrameSet(data.frames, data.pattern, data.grip_level, RANDOMIZED_EVAL_SEED)


def _accuracy(clf: Any, fs: FrameSet) -> tuple[float, np.ndarray]:
    a, p = clf.predict(fs.frames)
    pred = patterns_of(a, p)
    return float(np.mean(pred == fs.pattern)), pred


def _match_share(fs: FrameSet, pred: np.ndarray) -> float:
    render = RobotConfig().render
    ok = 0
    for k in range(len(fs)):
        stim = render_stimulus(fs.frames[k], int(pred[k]), method=render.method, order=render.order)
        ok += matches_pattern(stim, int(fs.pattern[k]))
    return ok / max(1, len(fs))


def classifier_tradeoff(
    models: list[Path],
    backends_for_default: list[str],
    backends_for_others: list[str],
    eval_default: FrameSet,
    eval_randomized: FrameSet | None,
    calls: int,
    paced_calls: int = 0,
    gap_s: float = 1 / 120,
) -> dict[str, Any]:
    """One row per (model, backend): latency, accuracy, match share, agreement.

    Latency is ``predict_one``, the robot node's call, back to back and with
    ``gap_s`` of sleep before each call (the node's situation: a core gone
    cold since the last frame). All classifiers are loaded first and timed in
    turn, call by call, so that the load drifting on a shared machine does
    not pick the winner.
    """
    rows: list[dict[str, Any]] = []
    loaded: list[tuple[dict[str, Any], Any]] = []
    timing_frames = [np.ascontiguousarray(f) for f in eval_default.frames[:512]]
    for path in models:
        info = _describe(path)
        is_default = info["model"] == "shipped default"
        reference: np.ndarray | None = None
        acc_default = acc_rand = match = None
        for backend in backends_for_default if is_default else backends_for_others:
            try:
                clf = load_classifier(path, backend, num_threads=1)
            except Exception as e:  # a missing optional backend is a row, not a crash
                rows.append({**info, "backend": backend, "error": str(e)})
                continue
            acc, pred = _accuracy(clf, eval_default)
            if reference is None:
                reference = pred
                acc_default = acc
                match = _match_share(eval_default, pred)
                if eval_randomized is not None:
                    acc_rand = _accuracy(clf, eval_randomized)[0]
            row = {
                **info,
                "backend": backend,
                "accuracy_default_generator": acc_default,
                "accuracy_randomized": acc_rand,
                "stimulus_match": match,
                "agrees_with_first_backend": float(np.mean(pred == reference)),
            }
            rows.append(row)
            loaded.append((row, clf))
    calls_of = [lambda i, c=clf, f=timing_frames: c.predict_one(f[i % len(f)]) for _, clf in loaded]
    times = time_interleaved(calls_of, calls, warmup=200)
    paced = (
        time_interleaved(calls_of, paced_calls, warmup=20, gap_s=gap_s)
        if paced_calls > 0
        else [None] * len(loaded)
    )
    for (row, _), samples, paced_samples in zip(loaded, times, paced, strict=True):
        t = summarize_ns(samples)
        row["median_us"] = t.median_us
        row["p99_us"] = t.p99_us
        if paced_samples is not None:
            tp = summarize_ns(paced_samples)
            row["paced_median_us"] = tp.median_us
            row["paced_p99_us"] = tp.p99_us
        log.info("classifier %s %s: %.1f us", row["model"], row["backend"], t.median_us)
    return {
        "paced_gap_s": gap_s if paced_calls > 0 else None,
        "eval_default_frames": len(eval_default),
        "eval_default_seed": eval_default.seed,
        "eval_randomized_frames": None if eval_randomized is None else len(eval_randomized),
        "eval_randomized_seed": RANDOMIZED_EVAL_SEED,
        "rows": rows,
        "backends_known": list(BACKENDS),
    }


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
        clf_calls=300,
        clf_paced_calls=60,
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
    from harness.bench.fixtures import frame_set
    from harness.bench.timing import limit_torch_threads

    eval_default = frame_set(sizes.clf_eval_repeats, seed=11)
    eval_rand = (
        randomized_eval_set(sizes.clf_randomized_repeats)
        if sizes.clf_randomized_repeats > 0
        else None
    )
    out = classifier_tradeoff(
        find_models(ctx.models),
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
        "sweep (`python -m harness.bench.perception_sweep --widths`, read from "
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
