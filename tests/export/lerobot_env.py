"""A separate environment holding LeRobot's own dataset class, to load exports with.

``lerobot-dataset`` 0.4.4 pins numpy 2.2, av<16 and datasets<4.2, and
imports torch and torchvision without declaring them, so it cannot share the
project's environment (docs/datasets.md). The venv is built once per
version set and cached outside the clone (``DEEPXPALM_LEROBOT_ENV``, or
``~/.cache/deepxpalm/``), so only the first run on a machine pays for the
install (about 5 minutes here, most of it unpacking torch). torch is the
project's CPU build, installed first so nothing pulls CUDA libraries.
"""

from __future__ import annotations

import os
import subprocess
import sys
import venv
from pathlib import Path

LEROBOT_DATASET = "lerobot-dataset==0.4.4"
TORCH = os.environ.get("TORCH", "torch==2.13.0")
TORCHVISION = "torchvision==0.28.0"  # the release built against torch 2.13
KEY = f"{LEROBOT_DATASET}-{TORCH}-{TORCHVISION}-py{sys.version_info[0]}{sys.version_info[1]}"
LOADER = Path(__file__).with_name("load_with_lerobot.py")


def env_dir() -> Path:
    base = os.environ.get("DEEPXPALM_LEROBOT_ENV")
    root = Path(base) if base else Path.home() / ".cache" / "deepxpalm"
    return root / KEY.replace("==", "-")


def ensure_env() -> Path:
    """The environment's python, building the environment if it is not there yet."""
    path = env_dir()
    python = path / "bin" / "python"
    stamp = path / ".installed"
    if stamp.exists():
        return python
    venv.EnvBuilder(with_pip=True, clear=True).create(path)
    pip = [str(python), "-m", "pip", "install", "-q", "--disable-pip-version-check"]
    subprocess.run([*pip, TORCH, TORCHVISION, LEROBOT_DATASET], check=True, timeout=1800)
    stamp.write_text(KEY + "\n")
    return python


def load_with_lerobot(root: Path, out_npz: Path, timeout_s: float = 300) -> None:
    """Load the dataset at ``root`` with ``LeRobotDataset``; every item goes to ``out_npz``."""
    python = ensure_env()
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "HF_DATASETS_OFFLINE": "1"}
    env["HF_HOME"] = str(out_npz.parent / "hf-home")  # its caches stay in the test's folder
    proc = subprocess.run(
        [str(python), str(LOADER), str(root), str(out_npz)],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        env=env,
    )
    if proc.returncode != 0:
        raise AssertionError(f"LeRobotDataset could not load {root}:\n{proc.stderr[-4000:]}")


if __name__ == "__main__":  # `make test` builds it before pytest, so tests time only themselves
    print(ensure_env())
