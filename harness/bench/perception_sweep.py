"""Batch-1 latency of every classifier backend, and model width against accuracy.

Not a test: numbers depend on the machine and on what else runs on it.
Run it on an otherwise idle robot PC and copy the tables into
docs/perception.md. Apart from ``deepxpalm bench`` because it trains: the
bench's classifier section compares the models this sweep writes to
runs/width-sweep, and trains none.

    python -m harness.bench.perception_sweep                      # shipped model, all backends
    python -m harness.bench.perception_sweep --cpu 1              # pinned to one core
    python -m harness.bench.perception_sweep --widths 0.125,0.25,0.5,1 --out runs/widths
    python -m harness.bench.perception_sweep --latency-of runs/widths/width-0.25.npz,...
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from robot_side.perception import BACKENDS, DEFAULT_MODEL, load_classifier
from robot_side.perception import dataset as ds

log = logging.getLogger(__name__)


def latency_us(classifier, frames: np.ndarray, calls: int, warmup: int = 300) -> np.ndarray:
    """Wall time of each of ``calls`` batch-1 ``predict`` calls, in microseconds."""
    singles = [np.ascontiguousarray(f[None]) for f in frames]
    for i in range(warmup):
        classifier.predict(singles[i % len(singles)])
    out = np.empty(calls)
    clock = time.perf_counter_ns
    for i in range(calls):
        x = singles[i % len(singles)]
        t = clock()
        classifier.predict(x)
        out[i] = clock() - t
    return out / 1e3


def cold_start_ms(model: Path, backend: str) -> float:
    """Fresh interpreter: import, load and first prediction, as the robot node pays it."""
    code = (
        "import time; t = time.perf_counter();"
        "import numpy as np;"
        "from robot_side.perception import load_classifier;"
        f"c = load_classifier({str(model)!r}, {backend!r});"
        "c.predict(np.zeros((1, 2, 10, 10), np.float32));"
        "print((time.perf_counter() - t) * 1e3)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return float(out.stdout.strip().splitlines()[-1])


def bench_backends(model: Path, backends: list[str], calls: int, frames: np.ndarray) -> list[dict]:
    rows = []
    for backend in backends:
        try:
            clf = load_classifier(model, backend, num_threads=1)
        except Exception as e:  # a missing optional backend is a row, not a crash
            log.warning("%s: unavailable (%s)", backend, e)
            continue
        t = latency_us(clf, frames, calls)
        rows.append(
            {
                "backend": backend,
                "median_us": float(np.median(t)),
                "p90_us": float(np.percentile(t, 90)),
                "p99_us": float(np.percentile(t, 99)),
                "cold_start_ms": cold_start_ms(model, backend),
            }
        )
    return rows


def print_backend_table(rows: list[dict], model: Path) -> None:
    print(f"\nbatch-1 predict, {model.name}, {len(rows)} backends (one thread each)\n")
    print("| backend | median (us) | p90 (us) | p99 (us) | import + load + first call (ms) |")
    print("|---|---:|---:|---:|---:|")
    for r in rows:
        print(
            f"| {r['backend']} | {r['median_us']:.1f} | {r['p90_us']:.1f} | {r['p99_us']:.1f} "
            f"| {r['cold_start_ms']:.0f} |"
        )


def width_sweep(widths: list[float], out: Path, epochs: int, repeats: int, calls: int) -> None:
    from robot_side.perception.train import ModelConfig, TrainConfig, run_training

    data = ds.generate(ds.DatasetConfig(repeats=repeats))
    frames = data.frames[:512]
    rows = []
    for width in widths:
        config = TrainConfig(epochs=epochs, model=ModelConfig(width=width))
        name = f"width-{width:g}"
        report = run_training(config, out, name, data=data, checkpoint=out / f"{name}.pt")
        rob = report["robustness"]
        lat = {}
        for backend in ("numpy", "onnxruntime"):
            clf = load_classifier(out / f"{name}.npz", backend, num_threads=1)
            t = latency_us(clf, frames, calls)
            lat[backend] = (float(np.median(t)), float(np.percentile(t, 99)))
        rows.append(
            {
                "width": width,
                "parameters": report["model"]["parameters"],
                "weights_kb": report["files"]["weights_bytes"] / 1024,
                "test_angle": report["test"]["angle_accuracy"],
                "test_position": report["test"]["position_accuracy"],
                "robust_angle_min": min(v["angle_accuracy"] for v in rob.values()),
                "robust_position_min": min(v["position_accuracy"] for v in rob.values()),
                "train_s": report["training"]["train_seconds"],
                "latency": lat,
            }
        )
        print(json.dumps(rows[-1]), flush=True)
    print(f"\nwidth sweep: {epochs} epochs, {len(data)} frames, seed 0\n")
    print(
        "| width | parameters | weights (KB) | test angle | test position | worst robustness "
        "angle | worst robustness position | train (s) | numpy median / p99 (us) "
        "| ONNX Runtime median / p99 (us) |"
    )
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        n, o = r["latency"]["numpy"], r["latency"]["onnxruntime"]
        print(
            f"| {r['width']:g} | {r['parameters']:,} | {r['weights_kb']:.0f} | "
            f"{r['test_angle']:.4f} | {r['test_position']:.4f} | {r['robust_angle_min']:.4f} | "
            f"{r['robust_position_min']:.4f} | {r['train_s']:.0f} | {n[0]:.1f} / {n[1]:.1f} | "
            f"{o[0]:.1f} / {o[1]:.1f} |"
        )


def latency_of(models: list[Path], calls: int, frames: np.ndarray) -> None:
    """Re-measure trained models (e.g. a width sweep's) without retraining them."""
    print("\n| model | parameters | numpy median / p99 (us) | ONNX Runtime median / p99 (us) |")
    print("|---|---:|---:|---:|")
    for path in models:
        cells = []
        for backend in ("numpy", "onnxruntime"):
            clf = load_classifier(path, backend, num_threads=1)
            t = latency_us(clf, frames, calls)
            cells.append(f"{np.median(t):.1f} / {np.percentile(t, 99):.1f}")
        params = clf.meta.get("parameters", 0)
        print(f"| {path.name} | {params:,} | {cells[0]} | {cells[1]} |", flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, default=DEFAULT_MODEL)
    parser.add_argument("--backends", default=",".join(BACKENDS))
    parser.add_argument("--calls", type=int, default=5000, help="timed calls per backend")
    parser.add_argument("--cpu", type=int, help="pin this process to one core")
    parser.add_argument("--widths", help="comma-separated widths to train and compare")
    parser.add_argument("--epochs", type=int, default=50)
    parser.add_argument("--repeats", type=int, default=ds.DatasetConfig().repeats)
    parser.add_argument("--out", type=Path, default=Path("runs/width-sweep"))
    parser.add_argument("--latency-of", help="comma-separated .npz models: latency only")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.cpu is not None:
        os.sched_setaffinity(0, {args.cpu})
    frames = ds.generate(ds.DatasetConfig(repeats=1, seed=99)).frames
    if args.latency_of:
        latency_of([Path(p) for p in args.latency_of.split(",")], args.calls, frames)
        return 0
    if args.widths:
        width_sweep(
            [float(w) for w in args.widths.split(",")],
            args.out,
            args.epochs,
            args.repeats,
            args.calls,
        )
        return 0
    rows = bench_backends(args.model, args.backends.split(","), args.calls, frames)
    print_backend_table(rows, args.model)
    return 0


if __name__ == "__main__":
    sys.exit(main())
