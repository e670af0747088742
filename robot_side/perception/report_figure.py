"""The training report as one PNG: curves, confusion matrices, grip levels, robustness."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")  # no display on a robot PC or in CI

import matplotlib.pyplot as plt
import numpy as np

ANGLE_LABELS = ["0°", "45°", "90°", "135°"]
POSITION_LABELS = ["centre", "left/up", "right/down"]


def _confusion(ax: Any, matrix: list[list[int]], labels: list[str], title: str) -> None:
    m = np.asarray(matrix, dtype=float)
    rows = m.sum(axis=1, keepdims=True)
    frac = np.divide(m, rows, out=np.zeros_like(m), where=rows > 0)
    ax.imshow(frac, cmap="Blues", vmin=0, vmax=1)
    for (r, c), v in np.ndenumerate(frac):
        ax.text(c, r, f"{v:.3f}", ha="center", va="center", color="white" if v > 0.5 else "black")
    ax.set_xticks(range(len(labels)), labels)
    ax.set_yticks(range(len(labels)), labels)
    ax.set_xlabel("predicted")
    ax.set_ylabel("true")
    ax.set_title(title)


def draw_report(report: dict[str, Any], path: str | Path) -> Path:
    """Write the figure for a report made by ``train.run_training``."""
    fig, axes = plt.subplots(2, 3, figsize=(16, 9.5))
    hist = report["training"]["history"]
    ep = [h["epoch"] for h in hist]
    ax = axes[0, 0]
    ax.plot(ep, [h["train_loss"] for h in hist], label="train loss")
    ax.plot(ep, [h["val_loss"] for h in hist], label="validation loss")
    ax.set_yscale("log")
    ax.set_xlabel("epoch")
    ax.legend()
    ax.set_title(f"loss (best epoch {report['training']['best_epoch']})")

    ax = axes[0, 1]
    ax.plot(ep, [h["val_angle_accuracy"] for h in hist], label="angle")
    ax.plot(ep, [h["val_position_accuracy"] for h in hist], label="position")
    ax.set_xlabel("epoch")
    ax.set_ylim(max(0.0, min(min(h["val_position_accuracy"] for h in hist), 0.9)), 1.0)
    ax.legend()
    ax.set_title("validation accuracy")

    test = report["test"]
    ax = axes[0, 2]
    levels = [k for k in test["per_grip_level"] if k != "unknown"]
    if levels:
        x = [int(k) for k in levels]
        ax.plot(
            x, [test["per_grip_level"][k]["angle_accuracy"] for k in levels], "o-", label="angle"
        )
        ax.plot(
            x, [test["per_grip_level"][k]["position_accuracy"] for k in levels], "s-",
            label="position",
        )  # fmt: skip
        ax.axhline(0.98, color="C0", lw=0.8, ls="--")
        ax.axhline(0.97, color="C1", lw=0.8, ls="--")
        ax.set_xlabel("grip level (1 = lightest)")
        ax.legend()
    ax.set_title("test accuracy per grip level")

    _confusion(
        axes[1, 0], test["angle_confusion"], ANGLE_LABELS,
        f"angle: test accuracy {test['angle_accuracy']:.4f}",
    )  # fmt: skip
    _confusion(
        axes[1, 1], test["position_confusion"], POSITION_LABELS,
        f"position: test accuracy {test['position_accuracy']:.4f}",
    )  # fmt: skip

    ax = axes[1, 2]
    rob = report.get("robustness") or {}
    if rob:
        names = list(rob)
        y = np.arange(len(names))
        ax.barh(y - 0.2, [rob[n]["angle_accuracy"] for n in names], 0.4, label="angle")
        ax.barh(y + 0.2, [rob[n]["position_accuracy"] for n in names], 0.4, label="position")
        ax.set_yticks(y, [n.replace("_", " ") for n in names])
        lo = min(min(rob[n]["angle_accuracy"], rob[n]["position_accuracy"]) for n in names)
        ax.set_xlim(max(0.0, min(lo, 0.93) - 0.02), 1.0)
        ax.axvline(0.95, color="C0", lw=0.8, ls="--")
        ax.axvline(0.93, color="C1", lw=0.8, ls="--")
        ax.legend(loc="lower left")
    ax.set_title("robustness: settings not trained with")
    m = report["model"]
    seconds = report["training"]["train_seconds"]
    fig.suptitle(
        f"TiltNet width {m['width']} ({m['parameters']:,} parameters), "
        f"{report['data']['frames']:,} frames, trained in {seconds:.0f} s"
    )
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path
