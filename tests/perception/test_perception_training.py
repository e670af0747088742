"""A tiny model trained for a few steps through `deepxpalm train`: files, report, backends."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from tests_support import needs

from deploy.cli import main as deepxpalm
from robot_side.perception import dataset as ds
from robot_side.perception import load_classifier

# no timing checked; torch is imported by the tests that run, not at collection (every test
# worker collects every module, and torch's import costs about 2 s of CPU)
pytestmark = [pytest.mark.slow, pytest.mark.untimed, needs("torch")]


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("train")
    data = ds.generate(ds.DatasetConfig(repeats=1, seed=1))
    data.save(out / "data.npz")
    code = deepxpalm(
        [
            "train",
            "--data", str(out / "data.npz"),
            "--out", str(out),
            "--name", "tiny",
            "--epochs", "2",
            "--width", "0.125",
            "--threads", "1",
            "--no-robustness",
            "--no-progress",
        ]
    )  # fmt: skip
    assert code == 0
    return out


def test_training_writes_weights_graph_and_report(tiny_run: Path) -> None:
    for name in ("tiny.npz", "tiny.onnx", "tiny.report.json", "tiny.report.png", "tiny.best.pt"):
        assert (tiny_run / name).is_file(), name
    report = json.loads((tiny_run / "tiny.report.json").read_text())
    test = report["test"]
    assert test["n"] == 372 - 186 - 93
    assert np.array(test["angle_confusion"]).shape == (4, 4)
    assert np.array(test["position_confusion"]).shape == (3, 3)
    assert np.array(test["angle_confusion"]).sum() == test["n"]
    assert set(test["per_grip_level"]) <= {str(g) for g in range(1, 32)}
    assert len(report["training"]["history"]) == 2
    assert report["model"]["width"] == 0.125


def test_trained_model_loads_in_every_backend_and_they_agree(tiny_run: Path) -> None:
    frames = ds.generate(ds.DatasetConfig(repeats=1, seed=2)).frames[:64]
    ref_a, ref_p = load_classifier(tiny_run / "tiny.npz", "torch").predict_proba(frames)
    for backend in ("numpy", "onnxruntime", "torchscript"):
        a, p = load_classifier(tiny_run / "tiny.npz", backend).predict_proba(frames)
        np.testing.assert_allclose(a, ref_a, atol=1e-5, err_msg=backend)
        np.testing.assert_allclose(p, ref_p, atol=1e-5, err_msg=backend)


def test_a_few_steps_reduce_the_loss() -> None:
    from robot_side.perception.model import ModelConfig
    from robot_side.perception.train import TrainConfig, train

    data = ds.generate(ds.DatasetConfig(repeats=1, seed=4))
    tr, va, _ = ds.split(data)
    config = TrainConfig(epochs=3, batch_size=32, threads=1, model=ModelConfig(width=0.125))
    result = train(config, tr, va)
    losses = [h["train_loss"] for h in result.history]
    assert losses[-1] < losses[0]
    assert result.best_epoch in (1, 2, 3)


def test_architecture_is_the_papers_at_width_1() -> None:
    import torch

    from robot_side.perception.model import PAPER_CONV, PAPER_HIDDEN, ModelConfig, TiltNet

    model = TiltNet(ModelConfig(width=1.0))
    convs = [m for m in model.backbone if isinstance(m, torch.nn.Conv2d)]
    norms = [m for m in model.backbone if isinstance(m, torch.nn.BatchNorm2d)]
    assert [c.out_channels for c in convs] == list(PAPER_CONV) and len(norms) == 2
    for head, n_out in ((model.angle_head, 4), (model.position_head, 3)):
        linears = [m for m in head if isinstance(m, torch.nn.Linear)]
        assert [(m.in_features, m.out_features) for m in linears] == [
            (3200, PAPER_HIDDEN[0]),
            (PAPER_HIDDEN[0], PAPER_HIDDEN[1]),
            (PAPER_HIDDEN[1], PAPER_HIDDEN[2]),
            (PAPER_HIDDEN[2], n_out),
        ]
    a, p = model.eval()(torch.zeros(3, 2, 10, 10))
    assert a.shape == (3, 4) and p.shape == (3, 3)


def test_train_defaults_round_trip_through_toml() -> None:
    import tomllib

    from common.config.typed import defaults_toml, from_dict
    from robot_side.perception.train import TrainConfig

    text = defaults_toml(TrainConfig, "train")
    assert "pipette_diameter_mm" in text and "[train.data.ranges]" in text
    assert from_dict(TrainConfig, tomllib.loads(text)["train"]) == TrainConfig()


def test_training_shows_the_projects_progress_bar_on_a_terminal(tiny_run: Path) -> None:
    """On a terminal, `deepxpalm train` draws common.progress's bar (with an ETA) on stderr."""
    import os
    import sys

    from tests_support import stderr_on_pty

    env = {k: v for k, v in os.environ.items() if k not in ("CI", "TERM")}
    argv = [sys.executable, "-m", "deploy.cli", "train", "--data", str(tiny_run / "data.npz"),
            "--out", str(tiny_run / "bar"), "--name", "bar", "--epochs", "2", "--width",
            "0.125", "--threads", "1", "--no-robustness"]  # fmt: skip
    seen, rc = stderr_on_pty(argv, env, cwd=Path(__file__).resolve().parents[2])
    text = seen.decode(errors="replace")
    assert rc == 0, text[-2000:]
    assert "\rtrain [" in text and "batches" in text and "ETA" in text, text[-2000:]
