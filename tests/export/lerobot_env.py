"""A separate environment holding LeRobot's own dataset class, to load exports with.

``lerobot-dataset`` 0.4.4 pins numpy 2.2, av<16 and datasets<4.2, and
imports torch and torchvision without declaring them, so it cannot share the
project's environment (docs/datasets.md). The venv is built once per
version set and cached outside the clone (``DEEPXPALM_LEROBOT_ENV``, or
``~/.cache/deepxpalm/``), so only the first run on a machine pays for the
install: torch with pip, installed first so nothing pulls CUDA libraries, the
rest with uv as ``make setup`` installs the project's (about a minute in all;
about 5 with pip alone, which it falls back to where uv is not there).
"""

from __future__ import annotations

import json
import os
import queue
import subprocess
import sys
import threading
import venv
from pathlib import Path

LEROBOT_DATASET = "lerobot-dataset==0.4.4"
TORCH = os.environ.get("TORCH", "torch==2.13.0")
TORCHVISION = "torchvision==0.28.0"  # the release built against torch 2.13
KEY = f"{LEROBOT_DATASET}-{TORCH}-{TORCHVISION}-py{sys.version_info[0]}{sys.version_info[1]}"
#: the uv options for the sources pip is configured with (``make setup`` uses it too)
UV_SOURCES = Path(__file__).resolve().parents[2] / "scripts" / "pip-config-as-uv-args.py"
#: answers the loads and the policies' questions (``load_with_lerobot.py``, ``policy_features.py``)
SERVER = Path(__file__).with_name("lerobot_server.py")
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


def _install(python: Path, *requirements: str) -> None:
    """``requirements`` into the environment: with uv where the project's setup installed it,
    from the sources pip is configured with (as ``make setup`` does), else with pip."""
    uv = Path(sys.executable).with_name("uv")
    if uv.exists():
        sources = subprocess.run(
            [sys.executable, str(UV_SOURCES)], capture_output=True, text=True, check=True
        ).stdout.split()
        cmd = [str(uv), "pip", "install", "-q", "--python", str(python), *sources, *requirements]
        if subprocess.run(cmd, timeout=1800).returncode == 0:
            return
    subprocess.run([*_pip(python), *requirements], check=True, timeout=1800)


def ensure_env() -> Path:
    """The environment's python, building the environment if it is not there yet."""
    path = env_dir()
    python = path / "bin" / "python"
    stamp = path / ".installed"
    if stamp.exists():
        return python
    venv.EnvBuilder(with_pip=True, clear=True).create(path)
    # torch with pip (the project's rule for torch: README.md), the rest as the project's are
    subprocess.run([*_pip(python), TORCH], check=True, timeout=1800)
    _install(python, TORCHVISION, LEROBOT_DATASET)
    stamp.write_text(KEY + "\n")
    return python


def ensure_policy_env() -> Path:
    """The same environment with ``lerobot`` added (its policies' configs); built once."""
    python = ensure_env()
    stamp = env_dir() / ".installed-policies"
    key = " ".join(LEROBOT_POLICIES) + "\n"
    if stamp.exists() and stamp.read_text() == key:
        return python
    _install(python, "--no-deps", *LEROBOT_POLICIES)
    stamp.write_text(key)
    return python


def ensure_video_decoder(python: Path) -> dict[str, str]:
    """torchcodec in the environment, and the variables that let it find FFmpeg; built once.

    No system FFmpeg is needed: PyAV (which ``lerobot-dataset`` installs) bundles one, under
    hashed names; a folder of links gives its libraries the names torchcodec opens.
    """
    stamp = env_dir() / ".installed-video"
    if not stamp.exists() or stamp.read_text() != TORCHCODEC + "\n":
        _install(python, "--no-deps", TORCHCODEC)
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


class LeRobot:
    """One interpreter in the LeRobot environment, answering every load a test module asks.

    Importing LeRobot costs about 12 s of CPU, loading a demo's dataset under a
    second or two: a module shares one (a module-scoped fixture) instead of
    starting the environment's python per load. ``policies`` builds the
    environment with ``lerobot`` itself (``policy_features`` needs it).
    """

    def __init__(self, work: Path, policies: bool = False) -> None:
        python = ensure_policy_env() if policies else ensure_env()
        env = {**os.environ, "HF_HUB_OFFLINE": "1", "HF_DATASETS_OFFLINE": "1"}
        env.update(ensure_video_decoder(python))
        env["HF_HOME"] = str(work / "hf-home")  # its caches stay in the test's folder
        self._stderr_path = work / "lerobot-server.stderr"
        self._stderr = self._stderr_path.open("w")
        self._proc = subprocess.Popen(
            [str(python), str(SERVER)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=self._stderr,
            text=True,
            env=env,
        )
        self._answers: queue.Queue[str | None] = queue.Queue()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self._proc.stdout:
            self._answers.put(line)
        self._answers.put(None)  # the server ended

    def _stderr_tail(self) -> str:
        self._stderr.flush()
        return self._stderr_path.read_text(errors="replace")[-4000:]

    def _ask(self, request: dict, timeout_s: float) -> dict:
        try:
            self._proc.stdin.write(json.dumps(request) + "\n")
            self._proc.stdin.flush()
            line = self._answers.get(timeout=timeout_s)
        except (BrokenPipeError, queue.Empty) as e:
            self._proc.kill()  # a server that does not answer answers nothing later either
            why = "did not answer in time" if isinstance(e, queue.Empty) else "had ended"
            raise AssertionError(f"LeRobot {why}:\n{self._stderr_tail()}") from None
        if line is None:
            raise AssertionError(f"LeRobot ended without answering:\n{self._stderr_tail()}")
        return json.loads(line)

    def load(self, root: Path, out_npz: Path, timeout_s: float = 300) -> None:
        """Load the dataset at ``root`` with ``LeRobotDataset``; every item goes to ``out_npz``."""
        reply = self._ask({"op": "load", "root": str(root), "out": str(out_npz)}, timeout_s)
        if not reply["ok"]:
            raise AssertionError(f"LeRobotDataset could not load {root}:\n{reply['error']}")

    def policy_features(self, root: Path, timeout_s: float = 300) -> dict:
        """What LeRobot's ACT and Diffusion configs make of the dataset at ``root``."""
        reply = self._ask({"op": "policy", "root": str(root)}, timeout_s)
        if not reply["ok"]:
            raise AssertionError(f"LeRobot could not derive policy features:\n{reply['error']}")
        return reply["result"]

    def close(self) -> None:
        # every answer is in: ended at once (its own exit, torch's and datasets' teardown,
        # takes seconds and checks nothing)
        self._proc.kill()
        self._proc.wait()
        self._reader.join(timeout=10)  # it reads to the end of the answers
        self._proc.stdin.close()
        self._proc.stdout.close()
        self._stderr.close()

    def __enter__(self) -> LeRobot:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


if __name__ == "__main__":  # `make test` builds it before pytest, so tests time only themselves
    python = ensure_policy_env()
    ensure_video_decoder(python)
    print(python)
