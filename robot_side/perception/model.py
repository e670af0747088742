"""The two-head tilt/position CNN (PyTorch), and how its weights are stored.

The architecture is the paper's: a backbone of two 3x3 convolutions, each
with batch norm and ReLU, at full 10x10 resolution; two heads of four fully
connected layers, one for the angle (4 classes), one for the position (3
classes). ``width`` scales every layer from the paper's size (16/32 channels,
heads 128-64-32), so a lab can trade accuracy for latency; the shipped
default is a measured choice (docs/perception.md).

One addition in front of the backbone, with no weights: the network sees each
pad twice, once in newtons scaled by the sensor's 9 N ceiling and once divided
by the frame's own peak. The second copy makes the band's shape independent
of how hard the gripper squeezes and of a pad's overall gain, which is what
lets a model trained on synthetic frames carry over to other sensors.

Weights live in an ``.npz`` (arrays named as in ``state_dict`` plus a JSON
``meta`` entry) so the NumPy and ONNX Runtime backends never import torch.
"""

from __future__ import annotations

import itertools
import json
import logging
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from common.config.typed import param
from common.tactile.contract import CONTACT_FLOOR_N, N_ANGLES, N_POSITIONS, SATURATION_N
from robot_side.perception.errors import ModelLoadError

log = logging.getLogger(__name__)

#: the paper's layer sizes, which ``width`` scales
PAPER_CONV = (16, 32)
PAPER_HIDDEN = (128, 64, 32)
FORMAT_VERSION = 1


@dataclass
class ModelConfig:
    width: float = param(
        0.25, "scale of every layer against the paper's 16/32 conv, 128-64-32 heads (measured)"
    )
    dropout: float = param(0.1, "dropout between head layers while training (none at inference)")

    def __post_init__(self) -> None:
        if not self.width > 0:
            raise ValueError(f"width must be positive, not {self.width!r}")
        if not 0 <= self.dropout < 1:
            raise ValueError(f"dropout must be in [0, 1), not {self.dropout!r}")

    @property
    def conv_channels(self) -> tuple[int, int]:
        return tuple(max(2, round(c * self.width)) for c in PAPER_CONV)  # type: ignore[return-value]

    @property
    def hidden(self) -> tuple[int, int, int]:
        return tuple(max(4, round(h * self.width)) for h in PAPER_HIDDEN)  # type: ignore[return-value]


class InputFeatures(nn.Module):
    """(N, 2, 10, 10) newtons -> (N, 4, 10, 10): scaled by 9 N and by the frame's peak."""

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        # the peak is clamped to at least the sensor floor before dividing by it
        peak = frames.amax(dim=(1, 2, 3), keepdim=True).clamp_min(CONTACT_FLOOR_N)
        return torch.cat([frames * (1.0 / SATURATION_N), frames / peak], dim=1)


def _head(n_in: int, hidden: tuple[int, int, int], n_out: int, dropout: float) -> nn.Sequential:
    layers: list[nn.Module] = []
    sizes = (n_in, *hidden)
    for a, b in itertools.pairwise(sizes):
        layers += [nn.Linear(a, b), nn.ReLU(), nn.Dropout(dropout)]
    layers.append(nn.Linear(sizes[-1], n_out))
    return nn.Sequential(*layers)


class TiltNet(nn.Module):
    """Backbone (conv-BN-ReLU x2) and two four-layer heads; returns both logits."""

    def __init__(self, config: ModelConfig | None = None) -> None:
        super().__init__()
        self.config = config = config or ModelConfig()
        c1, c2 = config.conv_channels
        self.features = InputFeatures()
        self.backbone = nn.Sequential(
            nn.Conv2d(4, c1, 3, padding=1),
            nn.BatchNorm2d(c1),
            nn.ReLU(),
            nn.Conv2d(c1, c2, 3, padding=1),
            nn.BatchNorm2d(c2),
            nn.ReLU(),
            nn.Flatten(),
        )
        n_feat = c2 * 10 * 10
        self.angle_head = _head(n_feat, config.hidden, N_ANGLES, config.dropout)
        self.position_head = _head(n_feat, config.hidden, N_POSITIONS, config.dropout)

    def forward(self, frames: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        f = self.backbone(self.features(frames))
        return self.angle_head(f), self.position_head(f)


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def save_weights(
    model: TiltNet, path: str | Path, extra_meta: dict[str, Any] | None = None
) -> Path:
    """Write the weights as ``.npz`` with the architecture in a JSON ``meta`` entry."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {k: v.detach().cpu().numpy() for k, v in model.state_dict().items()}
    meta = {
        "format_version": FORMAT_VERSION,
        "architecture": "TiltNet",
        "model": asdict(model.config),
        "conv_channels": list(model.config.conv_channels),
        "hidden": list(model.config.hidden),
        "parameters": count_parameters(model),
        **(extra_meta or {}),
    }
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    with path.open("wb") as f:
        np.savez(f, **arrays)
    return path


def build_from_weights(weights: dict[str, np.ndarray], meta: dict[str, Any]) -> TiltNet:
    """An eval-mode TiltNet holding ``weights`` (as read by ``read_weights``)."""
    config = ModelConfig(**meta["model"])
    model = TiltNet(config)
    state = {k: torch.from_numpy(np.array(v)) for k, v in weights.items()}
    try:
        model.load_state_dict(state)
    except RuntimeError as e:
        raise ModelLoadError(
            f"weights do not fit a TiltNet of width {config.width}: {e}; "
            "was the file written by a different version? retrain with `deepxpalm train`"
        ) from None
    return model.eval()


def export_onnx(model: TiltNet, path: str | Path, opset: int = 17) -> Path:
    """ONNX graph with a dynamic batch axis, for the ONNX Runtime backend.

    The TorchScript-based exporter (``dynamo=False``) is used because the
    dynamo exporter needs onnxscript, which the train extra does not install.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    model = model.eval()
    example = torch.zeros(1, 2, 10, 10)
    # The legacy exporter warns that it is legacy; it is the one that needs no onnxscript.
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(
            model,
            (example,),
            str(path),
            input_names=["frames"],
            output_names=["angle_logits", "position_logits"],
            dynamic_axes={
                "frames": {0: "batch"},
                "angle_logits": {0: "batch"},
                "position_logits": {0: "batch"},
            },
            opset_version=opset,
            dynamo=False,
        )
    return path
