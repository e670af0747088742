"""The perception study's protocol (the paper's section VI): settings, trial order, results file.

A session is one participant in one rendering mode: a training phase that
shows each of the 12 patterns with its picture while the palm feels it, a
blind practice round with feedback, then the test: each pattern
``repetitions`` times (5 in the paper, so 60 trials) in a seeded random
order. The order, and every simulated grasp, follow from the seed, so an
interrupted session resumes with exactly the trials it had left.

Results go to one JSON Lines file per participant and mode, one line per
trial, written, flushed and fsync'ed before the next trial starts: a crash
or a pulled plug loses at most the trial that was on the palm.
"""

from __future__ import annotations

import json
import logging
import os
import re
import zlib
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

import numpy as np

from common.config.typed import param, to_dict
from common.errors import ConfigError
from common.tactile.contract import N_GRIP_LEVELS, N_PATTERNS, SATURATION_N
from operator_side.palm.renderer import RendererConfig

log = logging.getLogger(__name__)

Mode = Literal["direct", "masked", "ideal"]
MODES: tuple[str, ...] = ("direct", "masked", "ideal")
FILE_VERSION = 1


@dataclass
class StudyConfig:
    mode: Mode = param(
        "masked",
        "direct: downsized frame, no mask (the paper's Table I); masked: the true pattern's "
        "mask applied (Table II); ideal: exactly the mask's cells, no sensor",
    )
    repetitions: int = param(5, "presentations of each pattern in the test (the paper: 5)")
    practice_rounds: int = param(
        1, "blind rounds of all 12 patterns with feedback after training (0: none)"
    )
    seed: int | None = param(
        None, "trial order and grasps; unset: derived from the participant id (stable)"
    )
    sensor_seed: int = param(0, "the simulated pads' fixed defects (direct and masked modes)")
    grip_level_min: int = param(16, "weakest simulated grip of a trial (1..31)")
    grip_level_max: int = param(N_GRIP_LEVELS, "strongest simulated grip of a trial (1..31)")
    ideal_force_n: float = param(5.0, "force of every pressed cell in ideal mode")
    frame_rate_hz: float = param(
        30.0, "new simulated frames per second: the stimulus carries the sensor's noise"
    )
    pause_s: float = param(1.5, "palm lifted between trials, so each pattern starts from off")
    feedback_s: float = param(1.5, "how long practice feedback stays on the page")
    servos: dict[str, Any] = param(
        {"kind": "in_memory"}, "LinkGlide servo bus: kind + settings, as [operator.servos]"
    )
    renderer: RendererConfig = param(RendererConfig(), "stimulus to servo goals, as the node's")

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {list(MODES)}, not {self.mode!r}")
        if not 1 <= self.repetitions <= 50:
            raise ValueError(f"repetitions must be 1..50, not {self.repetitions}")
        if not 0 <= self.practice_rounds <= 10:
            raise ValueError(f"practice_rounds must be 0..10, not {self.practice_rounds}")
        if not 1 <= self.grip_level_min <= self.grip_level_max <= N_GRIP_LEVELS:
            raise ValueError(
                f"grip levels must satisfy 1 <= grip_level_min <= grip_level_max <= {N_GRIP_LEVELS}"
            )
        if not 0 < self.ideal_force_n <= SATURATION_N:
            raise ValueError(
                f"ideal_force_n must be in (0, {SATURATION_N:g}] N, not {self.ideal_force_n}"
            )
        if not 0 < self.frame_rate_hz <= 120:
            raise ValueError(f"frame_rate_hz must be in (0, 120], not {self.frame_rate_hz}")
        if self.pause_s < 0 or self.feedback_s < 0:
            raise ValueError("pause_s and feedback_s must not be negative")


_PARTICIPANT = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]{0,63}$")


def check_participant(participant: str) -> str:
    """Participant ids become file names: letters, digits, ``-`` and ``_`` only."""
    if not _PARTICIPANT.match(participant):
        raise ConfigError(
            f"participant id {participant!r} must be 1-64 letters, digits, '-' or '_' "
            "(it names the results file; use a code, never a name)"
        )
    return participant


def session_seed(config: StudyConfig, participant: str) -> int:
    """The configured seed, or one derived from the id: each participant gets their own order."""
    if config.seed is not None:
        return int(config.seed)
    return zlib.crc32(participant.encode())


def trial_order(seed: int, repetitions: int) -> list[int]:
    """Each pattern ``repetitions`` times, shuffled by ``seed``."""
    rng = np.random.default_rng([seed, 0])
    return [int(p) for p in rng.permutation(np.repeat(np.arange(N_PATTERNS), repetitions))]


def practice_order(seed: int, rounds: int) -> list[int]:
    rng = np.random.default_rng([seed, 1])
    return [int(p) for _ in range(rounds) for p in rng.permutation(N_PATTERNS)]


def trial_rng(seed: int, phase: str, index: int) -> np.random.Generator:
    """The grasp of one trial, the same on a resumed session."""
    code = {"training": 2, "practice": 3, "test": 4}[phase]
    return np.random.default_rng([seed, code, index])


def results_path(out_dir: Path, participant: str, mode: str) -> Path:
    return Path(out_dir) / f"{check_participant(participant)}_{mode}.jsonl"


def now_wall() -> str:
    """Wall-clock time for people reading the file (never used for durations)."""
    return datetime.now(UTC).isoformat(timespec="milliseconds")


class ResultsFile:
    """One participant's trials in one mode: appended, flushed and fsync'ed line by line.

    Opening an existing file resumes it: the header must match (mode and
    seed), and the test trials already answered are reported by
    ``completed_test_trials`` so the runner skips them.
    """

    def __init__(self, path: Path, participant: str, mode: str, seed: int) -> None:
        self.path = Path(path)
        self.participant, self.mode, self.seed = participant, mode, seed
        self.records = read_records(self.path) if self.path.exists() else []
        for rec in self.records:
            if rec.get("kind") == "session" and (rec["mode"], rec["seed"]) != (mode, seed):
                raise ConfigError(
                    f"{self.path} holds a {rec['mode']} session with seed {rec['seed']}; "
                    f"resume it with --seed {rec['seed']}, or use another participant id"
                )
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = self.path.open("a", encoding="utf-8")
        if self._file.tell() > 0 and not self.path.read_bytes().endswith(b"\n"):
            self._file.write("\n")  # a line torn by a crash stays on its own

    @property
    def resumed(self) -> bool:
        return any(r.get("kind") == "session" for r in self.records)

    def completed_test_trials(self) -> set[int]:
        return {
            int(r["index"])
            for r in self.records
            if r.get("kind") == "trial" and r.get("phase") == "test"
        }

    def append(self, record: dict[str, Any]) -> None:
        self._file.write(json.dumps(record, separators=(",", ":")) + "\n")
        self._file.flush()
        os.fsync(self._file.fileno())
        self.records.append(record)

    def write_header(self, config: StudyConfig, ui: str) -> None:
        self.append(
            {
                "kind": "session",
                "version": FILE_VERSION,
                "participant": self.participant,
                "mode": self.mode,
                "seed": self.seed,
                "resumed": self.resumed,
                "ui": ui,
                "started": now_wall(),
                "config": to_dict(config),
            }
        )

    def close(self) -> None:
        self._file.close()


def read_records(path: Path) -> list[dict[str, Any]]:
    """Every well-formed line; a torn last line (a crash mid-write) is skipped with a warning."""
    out = []
    with Path(path).open(encoding="utf-8") as f:
        for n, line in enumerate(f, 1):
            if not line.strip():
                continue
            try:
                rec = json.loads(line)
            except ValueError:
                log.warning("%s:%d: skipping a line that is not JSON (torn by a crash?)", path, n)
                continue
            if isinstance(rec, dict):
                out.append(rec)
    return out
