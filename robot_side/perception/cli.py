"""``deepxpalm train``: generate data, train the tilt CNN, export it, report it.

Typical uses::

    deepxpalm train                                       # synthetic data -> runs/perception
    deepxpalm train --data lab_frames.npz --init default  # fine-tune on a lab's recorded frames
    deepxpalm train --generate-only --save-data data.npz  # just the data set
    deepxpalm train --ship                                # rebuild the shipped default model
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

from common.config.typed import from_dict, load_toml
from common.errors import ConfigError
from common.tactile.contract import N_GRIP_LEVELS, N_PATTERNS
from robot_side.perception.weights import DEFAULT_MODEL, MODELS_DIR


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", type=Path, help="TOML file with a [train] table (TrainConfig)")
    parser.add_argument("--out", type=Path, default=Path("runs/perception"), help="output folder")
    parser.add_argument("--name", default="model", help="file stem of the outputs")
    parser.add_argument(
        "--ship",
        action="store_true",
        help=f"write the shipped default model ({MODELS_DIR.name}/{DEFAULT_MODEL.stem}.*)",
    )
    parser.add_argument(
        "--data",
        type=Path,
        help="train on this .npz (e.g. recorded frames) or a dataset `deepxpalm export` wrote",
    )
    parser.add_argument(
        "--labels",
        choices=["truth", "recognised"],
        default="truth",
        help="exported datasets: the simulator's true pattern (default) or the recognised one",
    )
    parser.add_argument("--save-data", type=Path, help="also save the generated data set here")
    parser.add_argument("--generate-only", action="store_true", help="generate data, no training")
    parser.add_argument(
        "--init", help="start from these weights (.npz, or 'default' for the shipped model)"
    )
    parser.add_argument("--epochs", type=int, help="training epochs (default 50)")
    parser.add_argument("--width", type=float, help="layer scale against the paper's sizes")
    parser.add_argument("--repeats", type=int, help="frames per (pattern, grip level)")
    parser.add_argument("--batch-size", type=int, help="mini-batch size")
    parser.add_argument("--lr", type=float, help="starting learning rate")
    parser.add_argument("--seed", type=int, help="seed of the data set and of training")
    parser.add_argument("--threads", type=int, help="torch threads (default 2)")
    parser.add_argument("--no-robustness", action="store_true", help="skip the robustness sets")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument(
        "--defaults", action="store_true", help="print every setting with its reason, as TOML"
    )


def _config(args: argparse.Namespace):
    from robot_side.perception.train import TrainConfig

    data = load_toml(args.config).get("train", {}) if args.config else {}
    config = from_dict(TrainConfig, data, where="train")
    try:
        if args.epochs is not None:
            config = dataclasses.replace(config, epochs=args.epochs)
        if args.batch_size is not None:
            config = dataclasses.replace(config, batch_size=args.batch_size)
        if args.lr is not None:
            config = dataclasses.replace(config, lr=args.lr)
        if args.threads is not None:
            config = dataclasses.replace(config, threads=args.threads)
        if args.width is not None:
            config = dataclasses.replace(
                config, model=dataclasses.replace(config.model, width=args.width)
            )
        if args.repeats is not None:
            config = dataclasses.replace(
                config, data=dataclasses.replace(config.data, repeats=args.repeats)
            )
        if args.seed is not None:
            config = dataclasses.replace(
                config, seed=args.seed, data=dataclasses.replace(config.data, seed=args.seed)
            )
    except ValueError as e:
        raise ConfigError(f"train: {e}") from None
    return config


def run(args: argparse.Namespace) -> int:
    from robot_side.perception import dataset as ds

    if args.defaults:
        from common.config.typed import defaults_toml
        from robot_side.perception.train import TrainConfig

        print(defaults_toml(TrainConfig, "train"), end="")
        return 0
    config = _config(args)
    out, name = (MODELS_DIR, DEFAULT_MODEL.stem) if args.ship else (args.out, args.name)
    progress = not args.no_progress and sys.stderr.isatty()

    data_seconds = None
    if args.data is not None:
        data = ds.load(args.data, labels=args.labels)
        print(f"loaded {len(data)} frames from {args.data}")
    else:
        n = config.data.repeats * N_PATTERNS * N_GRIP_LEVELS
        print(f"generating {n} frames (seed {config.data.seed}) ...", flush=True)
        t0 = time.monotonic()
        data = ds.generate(config.data)
        data_seconds = time.monotonic() - t0
        print(f"generated {n} frames in {data_seconds:.1f} s")
    if args.save_data is not None:
        data.save(args.save_data)
        print(f"saved the data set to {args.save_data}")
    if args.generate_only:
        return 0

    from robot_side.perception.train import run_training

    init = DEFAULT_MODEL if args.init == "default" else args.init
    m = config.model
    print(f"training width {m.width} for {config.epochs} epochs on {config.threads} threads")

    def on_epoch(row: dict) -> None:
        line = (
            f"epoch {row['epoch']:3d}  train loss {row['train_loss']:.4f}  "
            f"val loss {row['val_loss']:.4f}  val angle {row['val_angle_accuracy']:.4f}  "
            f"val position {row['val_position_accuracy']:.4f}  lr {row['lr']:.2g}  "
            f"{row['seconds']:.0f} s"
        )
        print(line, flush=True)  # training took the bar off the line first

    report = run_training(
        config,
        out,
        name,
        data=data,
        init_weights=init,
        checkpoint=args.out / f"{name}.best.pt",
        robustness=not args.no_robustness,
        data_seconds=data_seconds,
        on_epoch=on_epoch,
        progress=progress,
    )
    test = report["test"]
    print(
        f"test: angle {test['angle_accuracy']:.4f}, position {test['position_accuracy']:.4f} "
        f"({test['n']} frames, best epoch {report['training']['best_epoch']}, "
        f"{report['training']['train_seconds']:.0f} s training)"
    )
    for set_name, r in report.get("robustness", {}).items():
        a, p = r["angle_accuracy"], r["position_accuracy"]
        print(f"robustness {set_name}: angle {a:.4f}, position {p:.4f}")
    print(f"wrote {out / (name + '.npz')}, .onnx, .report.json, .report.png")
    print(json.dumps({"angle": test["angle_accuracy"], "position": test["position_accuracy"]}))
    return 0
