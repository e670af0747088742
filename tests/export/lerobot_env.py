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

import json
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
POLICY_FEATURES = Path(__file__).with_name("policy_features.py")
#: ``lerobot`` itself, for its policies' configs, on top of the same environment: without
#: its dependencies (they pin torch<2.11, which would pull CUDA), plus what importing
#: ``LeRobotDataset``, ``ACTConfig`` and ``DiffusionConfig`` needs, measured by importing them
LEROBOT_POLICIES = [
    "lerobot==0.4.4",
    "draccus==0.10.0",
    "accelerate==1.15.0",
    "safetensors==0.8.0",
    "typing-inspect==0.9.0",
    "mypy-extensions==1.2.0",
    "mergedeep==1.3.4",
    "diffusers==0.35.2",
    "pyserial==3.5",
    "einops==0.8.2",
]
#: LeRobot's video decoder: its pyav path needs torchvision's VideoReader, which torchvision
#: 0.28 no longer has, so torchcodec (the release built for torch 2.13) decodes the videos
TORCHCODEC = "torchcodec==0.13.0"
#: the FFmpeg libraries torchcodec opens by their usual names (libavcodec.so.61, ...); the
#: environment has them as PyAV's bundled copies, renamed by auditwheel
FFMPEG_LIBS = ("avcodec", "avdevice", "avfilter", "avformat", "avutil", "swresample", "swscale")


def env_dir() -> Path:
    base = os.environ.get("DEEPXPALM_LEROBOT_ENV")
    root = Path(base) if base else Path.home() / ".cache" / "deepxpalm"
    return root / KEY.replace("==", "-")


def _pip(python: Path) -> list[str]:
    """pip install in the environment; --no-compile: modules compile at first import."""
    quiet = ["-q", "--disable-pip-version-check"]
    return [str(python), "-m", "pip", "install", *quiet, "--no-compile"]


def ensure_env() -> Path:
    """The environment's python, building the environment if it is not there yet."""
    path = env_dir()
    python = path / "bin" / "python"
    stamp = path / ".installed"
    if stamp.exists():
        return python
    venv.EnvBuilder(with_pip=True, clear=True).create(path)
    subprocess.run([*_pip(python), TORCH, TORCHVISION, LEROBOT_DATASET], check=True, timeout=1800)
    stamp.write_text(KEY + "\n")
    return python


def ensure_policy_env() -> Path:
    """The same environment with ``lerobot`` added (its policies' configs); built once."""
    python = ensure_env()
    stamp = env_dir() / ".installed-policies"
    key = " ".join(LEROBOT_POLICIES) + "\n"
    if stamp.exists() and stamp.read_text() == key:
        return python
    subprocess.run([*_pip(python), "--no-deps", *LEROBOT_POLICIES], check=True, timeout=1800)
    stamp.write_text(key)
    return python


def ensure_video_decoder(python: Path) -> dict[str, str]:
    """torchcodec in the environment, and the variables that let it find FFmpeg; built once.

    No system FFmpeg is needed: PyAV (which ``lerobot-dataset`` installs) bundles one, under
    hashed names; a folder of links gives its libraries the names torchcodec opens.
    """
    stamp = env_dir() / ".installed-video"
    if not stamp.exists() or stamp.read_text() != TORCHCODEC + "\n":
        subprocess.run([*_pip(python), "--no-deps", TORCHCODEC], check=True, timeout=1800)
        stamp.write_text(TORCHCODEC + "\n")
    bundled = next((env_dir() / "lib").glob("python3*/site-packages/av.libs"))
    links = env_dir() / "ffmpeg-links"
    links.mkdir(exist_ok=True)
    for lib in bundled.iterdir():
        name, _, version = lib.name.partition(".so.")
        base = name.rsplit("-", 1)[0].removeprefix("lib")
        if base in FFMPEG_LIBS:
            link = links / f"lib{base}.so.{version.split('.')[0]}"
            if not link.exists():
                link.symlink_to(lib)
    paths = [str(links), str(bundled), os.environ.get("LD_LIBRARY_PATH", "")]
    return {"LD_LIBRARY_PATH": os.pathsep.join(p for p in paths if p)}


def load_with_lerobot(root: Path, out_npz: Path, timeout_s: float = 300) -> None:
    """Load the dataset at ``root`` with ``LeRobotDataset``; every item goes to ``out_npz``."""
    python = ensure_env()
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "HF_DATASETS_OFFLINE": "1"}
    env.update(ensure_video_decoder(python))
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


def policy_features(root: Path, work: Path, timeout_s: float = 300) -> dict:
    """What LeRobot's ACT and Diffusion configs make of the dataset at ``root``."""
    python = ensure_policy_env()
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "HF_DATASETS_OFFLINE": "1"}
    env.update(ensure_video_decoder(python))
    env["HF_HOME"] = str(work / "hf-home")
    proc = subprocess.run(
        [str(python), str(POLICY_FEATURES), str(root)],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        env=env,
    )
    if proc.returncode != 0:
        raise AssertionError(f"LeRobot could not derive policy features:\n{proc.stderr[-4000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


if __name__ == "__main__":  # `make test` builds it before pytest, so tests time only themselves
    python = ensure_policy_env()
    ensure_video_decoder(python)
    print(python)
