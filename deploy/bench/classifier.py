"""Classifier: backends and model widths, batch-1 latency against accuracy.

No model is trained here (two cores are shared): the shipped model and any
other model files found (``--models``, e.g. the perception engineer's width
sweep in runs/width-sweep) are measured as they are. Accuracy is on seeded
frames none of them were trained on: the default pad model over every
pattern and grip level, and a domain-randomised set drawn like the training
data but from another seed. The stimulus match share is the end result:
the predicted pattern's mask, rendered with the node's defaults, against
the true pattern.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from common.stimulus import render_stimulus
from common.tactile import matches_pattern, patterns_of
from deploy.bench.fixtures import FrameSet
from deploy.bench.timing import summarize_ns, time_interleaved
from robot_side.config import RobotConfig
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
