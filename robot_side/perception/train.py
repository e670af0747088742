"""Training the tilt CNN, choosing its best epoch, and writing its report.

The loop is the paper's: cross-entropy on each head, summed; Adam with
ReduceLROnPlateau on the validation loss; 50 epochs by default. The epoch
kept is the one with the best validation accuracy (both heads averaged), so
a late bad epoch never ships. The report gives what the issue asks of a
shipped model: accuracy per head, both confusion matrices, accuracy per grip
level on the held-out test split, and the same on generator settings the
model never saw (more noise, a wider pipette, more dead taxels).
"""

from __future__ import annotations

import copy
import dataclasses
import json
import logging
import os
import platform
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from common.config.typed import param, to_dict
from common.tactile.contract import N_GRIP_LEVELS, N_PATTERNS
from common.tactile.synthetic import GeneratorParams
from robot_side.perception import dataset as ds
from robot_side.perception.model import (
    ModelConfig,
    TiltNet,
    count_parameters,
    export_onnx,
    save_weights,
)
from robot_side.perception.weights import read_weights

log = logging.getLogger(__name__)

ANGLE_LABELS = ["0", "45", "90", "135"]
POSITION_LABELS = ["centre", "left/up", "right/down"]


@dataclass
class TrainConfig:
    epochs: int = param(50, "the paper's 50 epochs")
    batch_size: int = param(128, "small enough for many updates per epoch on a 2-core CPU")
    lr: float = param(2e-3, "Adam's starting learning rate")
    weight_decay: float = param(1e-4, "light L2 (AdamW) against memorising one sensor's defects")
    lr_factor: float = param(0.5, "ReduceLROnPlateau: multiply the rate by this on a plateau")
    lr_patience: int = param(3, "ReduceLROnPlateau: epochs without a better validation loss")
    split_seed: int = param(0, "seeds the 50/25/25 split, so the test set can be rebuilt")
    seed: int = param(0, "seeds weights and batch order")
    threads: int = param(2, "torch threads: the robot PC has two cores")
    robustness_repeats: int = param(
        4, "frames per (pattern, grip level) in each robustness set (12 x 31 x this)"
    )
    model: ModelConfig = param(ModelConfig(), "network size")
    data: ds.DatasetConfig = param(ds.DatasetConfig(), "the synthetic data set")

    def __post_init__(self) -> None:
        if self.epochs < 1 or self.batch_size < 1 or self.threads < 1:
            raise ValueError("epochs, batch_size and threads must be at least 1")
        if not self.lr > 0:
            raise ValueError("lr must be positive")


def robustness_settings() -> dict[str, GeneratorParams]:
    """Generator settings outside the training ranges (dataset.RandomizationRanges)."""
    base = GeneratorParams()
    noisy = {"noise_n": 0.4, "noise_relative": 0.08}  # trained up to 0.25 N and 0.05
    wide = {"pipette_diameter_mm": 11.0}  # trained on 4 to 7.5 mm (bands up to 10.5 mm)
    dead = {"dead_taxel_fraction": 0.1}  # trained up to 4 %
    return {
        "default_generator": base,
        "more_noise": dataclasses.replace(base, **noisy),
        "wider_pipette": dataclasses.replace(base, **wide),
        "more_dead_taxels": dataclasses.replace(base, **dead),
        "all_three": dataclasses.replace(base, **noisy, **wide, **dead),
    }


@dataclass
class TrainResult:
    model: TiltNet
    history: list[dict[str, float]]
    best_epoch: int
    seconds: float


def _tensors(data: ds.TactileDataset) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    return (
        torch.from_numpy(np.ascontiguousarray(data.frames)),
        torch.from_numpy(data.angle),
        torch.from_numpy(data.position),
    )


@torch.no_grad()
def logits_of(
    model: nn.Module, frames: np.ndarray, batch: int = 2048
) -> tuple[np.ndarray, np.ndarray]:
    """Eval-mode logits of many frames, in batches."""
    model.eval()
    outs_a, outs_p = [], []
    x = torch.from_numpy(np.ascontiguousarray(frames, dtype=np.float32))
    for i in range(0, len(x), batch):
        a, p = model(x[i : i + batch])
        outs_a.append(a.numpy())
        outs_p.append(p.numpy())
    if not outs_a:
        return np.zeros((0, 4), np.float32), np.zeros((0, 3), np.float32)
    return np.concatenate(outs_a), np.concatenate(outs_p)


def train(
    config: TrainConfig,
    train_set: ds.TactileDataset,
    val_set: ds.TactileDataset,
    *,
    init_weights: str | Path | None = None,
    checkpoint: str | Path | None = None,
    on_epoch: Callable[[dict[str, float]], None] | None = None,
    progress: bool = False,
    max_steps: int | None = None,
) -> TrainResult:
    """Train a TiltNet and return it at its best validation epoch.

    ``init_weights`` starts from an existing model (fine-tuning the shipped
    one on a lab's recorded frames); ``checkpoint`` is rewritten with each new
    best epoch so an interrupted run keeps its best; ``max_steps`` stops
    early (the test suite trains only a few steps).
    """
    torch.set_num_threads(config.threads)
    torch.manual_seed(config.seed)
    model = TiltNet(config.model)
    if init_weights is not None:
        from robot_side.perception.model import build_from_weights

        weights, meta = read_weights(init_weights)
        model = build_from_weights(weights, meta)
        config = dataclasses.replace(config, model=model.config)
    x, ya, yp = _tensors(train_set)
    vx, vya, vyp = _tensors(val_set)
    opt = torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    sched = torch.optim.lr_scheduler.ReduceLROnPlateau(
        opt, mode="min", factor=config.lr_factor, patience=config.lr_patience
    )
    loss_fn = nn.CrossEntropyLoss()
    gen = torch.Generator().manual_seed(config.seed)
    n_batches = max(1, -(-len(x) // config.batch_size))
    bar = None
    if progress:  # the project's one progress bar (common/progress.py): on stderr, with an ETA
        from common.progress import Progress

        bar = Progress("train", config.epochs * n_batches, unit="batches")
    history: list[dict[str, float]] = []
    best_score, best_state, best_epoch = -1.0, copy.deepcopy(model.state_dict()), 0
    steps = 0
    t0 = time.monotonic()
    try:
        for epoch in range(1, config.epochs + 1):
            model.train()
            order = torch.randperm(len(x), generator=gen)
            total, seen = 0.0, 0
            for i in range(0, len(x), config.batch_size):
                idx = order[i : i + config.batch_size]
                if len(idx) < 2:  # batch norm needs two samples
                    continue
                la, lp = model(x[idx])
                loss = loss_fn(la, ya[idx]) + loss_fn(lp, yp[idx])
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                total += loss.item() * len(idx)
                seen += len(idx)
                steps += 1
                if bar is not None:
                    bar.advance()
                if max_steps is not None and steps >= max_steps:
                    break
            model.eval()
            with torch.no_grad():
                va, vp = model(vx)
                val_loss = float(loss_fn(va, vya) + loss_fn(vp, vyp))
                acc_a = float((va.argmax(1) == vya).float().mean())
                acc_p = float((vp.argmax(1) == vyp).float().mean())
            sched.step(val_loss)
            row = {
                "epoch": epoch,
                "train_loss": total / max(seen, 1),
                "val_loss": val_loss,
                "val_angle_accuracy": acc_a,
                "val_position_accuracy": acc_p,
                "lr": opt.param_groups[0]["lr"],
                "seconds": time.monotonic() - t0,
            }
            history.append(row)
            score = (acc_a + acc_p) / 2
            if score > best_score:
                best_score, best_epoch = score, epoch
                best_state = copy.deepcopy(model.state_dict())
                if checkpoint is not None:
                    torch.save({"state_dict": best_state, "epoch": epoch}, checkpoint)
            if bar is not None:
                detail = f"epoch {epoch}: val angle {acc_a:.4f}, position {acc_p:.4f}"
                bar.update(steps, detail=detail, draw=False)
                bar.clear()  # the epoch's line (on_epoch, the log) above it; the next step redraws
            log.info(
                "epoch %d: train loss %.4f, val loss %.4f, val angle %.4f, position %.4f",
                epoch, row["train_loss"], val_loss, acc_a, acc_p,
            )  # fmt: skip
            if on_epoch is not None:
                on_epoch(row)
            if max_steps is not None and steps >= max_steps:
                break
    finally:
        if bar is not None:
            bar.close()
    model.load_state_dict(best_state)
    model.eval()
    return TrainResult(model, history, best_epoch, time.monotonic() - t0)


# --- evaluation ---------------------------------------------------------


def confusion(truth: np.ndarray, pred: np.ndarray, n: int) -> list[list[int]]:
    """Counts, rows = true class, columns = predicted class."""
    m = np.zeros((n, n), dtype=np.int64)
    np.add.at(m, (truth, pred), 1)
    return m.tolist()


def evaluate(
    angle_pred: np.ndarray, position_pred: np.ndarray, data: ds.TactileDataset
) -> dict[str, Any]:
    """Accuracy per head, both confusion matrices, and accuracy per grip level."""
    ok_a = angle_pred == data.angle
    ok_p = position_pred == data.position
    per_level = {}
    for level in np.unique(data.grip_level):
        sel = data.grip_level == level
        key = str(int(level)) if level > 0 else "unknown"
        per_level[key] = {
            "n": int(sel.sum()),
            "angle_accuracy": float(ok_a[sel].mean()),
            "position_accuracy": float(ok_p[sel].mean()),
        }
    n = len(data)
    return {
        "n": n,
        "angle_accuracy": float(ok_a.mean()) if n else float("nan"),
        "position_accuracy": float(ok_p.mean()) if n else float("nan"),
        "both_accuracy": float((ok_a & ok_p).mean()) if n else float("nan"),
        "angle_confusion": confusion(data.angle, angle_pred, 4),
        "position_confusion": confusion(data.position, position_pred, 3),
        "per_grip_level": per_level,
    }


def evaluate_model(model: nn.Module, data: ds.TactileDataset) -> dict[str, Any]:
    a, p = logits_of(model, data.frames)
    return evaluate(a.argmax(1), p.argmax(1), data)


def robustness_report(model: nn.Module, repeats: int, seed: int = 1000) -> dict[str, Any]:
    """Accuracy on each of ``robustness_settings``, freshly generated from ``seed``."""
    out = {}
    base = dataclasses.asdict(GeneratorParams())
    for i, (name, params) in enumerate(robustness_settings().items()):
        data = ds.generate_with(params, repeats=repeats, seed=seed + i)
        result = evaluate_model(model, data)
        changed = {k: v for k, v in dataclasses.asdict(params).items() if base[k] != v}
        out[name] = {"changed": changed, **result}
    return out


# --- the whole run ------------------------------------------------------


def run_training(
    config: TrainConfig,
    out_dir: str | Path,
    name: str = "model",
    *,
    data: ds.TactileDataset | None = None,
    init_weights: str | Path | None = None,
    checkpoint: str | Path | None = None,
    robustness: bool = True,
    data_seconds: float | None = None,
    on_epoch: Callable[[dict[str, float]], None] | None = None,
    progress: bool = False,
    max_steps: int | None = None,
) -> dict[str, Any]:
    """Generate (or take) data, train, export ``name``.npz/.onnx, write the report.

    Returns the report, also written as ``name``.report.json and .png.
    ``data_seconds`` is what generating ``data`` cost, when the caller did it.
    ``checkpoint`` (a torch ``.pt``) keeps the best epoch while training runs;
    it is not needed afterwards and does not belong beside a shipped model.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.monotonic()
    if checkpoint is not None:
        Path(checkpoint).parent.mkdir(parents=True, exist_ok=True)
    if data is None:
        log.info("generating %d frames", config.data.repeats * N_PATTERNS * N_GRIP_LEVELS)
        data = ds.generate(config.data)
        data_seconds = time.monotonic() - t_start
    train_set, val_set, test_set = ds.split(data, seed=config.split_seed)
    result = train(
        config,
        train_set,
        val_set,
        init_weights=init_weights,
        checkpoint=checkpoint,
        on_epoch=on_epoch,
        progress=progress,
        max_steps=max_steps,
    )
    model = result.model
    test = evaluate_model(model, test_set)
    report: dict[str, Any] = {
        "model": {
            "width": model.config.width,
            "conv_channels": list(model.config.conv_channels),
            "hidden": list(model.config.hidden),
            "parameters": count_parameters(model),
        },
        "data": {
            "source": data.meta.get("source", "recorded"),
            "frames": len(data),
            "train": len(train_set),
            "validation": len(val_set),
            "test": len(test_set),
            "split_seed": config.split_seed,
        },
        "training": {
            "config": to_dict(config),
            "best_epoch": result.best_epoch,
            "epochs_run": len(result.history),
            "train_seconds": result.seconds,
            "data_seconds": data_seconds,
            "threads": config.threads,
            "cpu_count": os.cpu_count(),
            "machine": platform.processor() or platform.machine(),
            "torch": torch.__version__,
            "history": result.history,
        },
        "test": test,
    }
    if robustness:
        report["robustness"] = robustness_report(model, config.robustness_repeats)
    meta = {
        "trained": {
            "best_epoch": result.best_epoch,
            "test_angle_accuracy": test["angle_accuracy"],
            "test_position_accuracy": test["position_accuracy"],
            "data_frames": len(data),
        }
    }
    weights_path = save_weights(model, out / f"{name}.npz", extra_meta=meta)
    onnx_path = export_onnx(model, out / f"{name}.onnx")
    report["files"] = {
        "weights": weights_path.name,
        "onnx": onnx_path.name,
        "weights_bytes": weights_path.stat().st_size,
        "onnx_bytes": onnx_path.stat().st_size,
    }
    report["total_seconds"] = time.monotonic() - t_start
    (out / f"{name}.report.json").write_text(json.dumps(report, indent=1) + "\n")
    try:
        from robot_side.perception.report_figure import draw_report

        draw_report(report, out / f"{name}.report.png")
    except ImportError as e:
        log.warning("no report figure (%s): install the train extra for matplotlib", e)
    return report
