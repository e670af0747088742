"""Tactile data sets: generate, save, load and split.

File format (``.npz``, NumPy's zip of arrays; no pickles):

========== ================ ==============================================
key        dtype, shape     meaning
========== ================ ==============================================
frames     float32 (N,2,10,10) newtons, common view (finger 2 mirrored)
angle      int64 (N,)       0..3 = 0, 45, 90, 135 deg
position   int64 (N,)       0..2 = centre, left (up at 0 deg), right (down)
grip_level int64 (N,)       1..31; 0 = unknown (optional, for real frames)
sensor     int64 (N,)       which simulated sensor / recording session (optional)
meta       uint8 bytes      UTF-8 JSON: how the set was made (optional)
========== ================ ==============================================

A recorded file may give ``pattern`` (= 3 * angle + position) instead of
``angle`` and ``position``. That is all a lab needs to retrain on its own
sensor: save its frames with their labels under these keys.

Synthetic sets use domain randomisation: frames come in sessions, and each
session is a new simulated sensor (fresh dead/stuck taxels and gains) whose
generator parameters are drawn from ``RandomizationRanges``. A classifier
that has seen pipettes of several diameters, pads of several softnesses and
sensors of several noise levels learns the band, not one simulator's quirks.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import zipfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from common.config.typed import param, to_dict
from common.tactile.contract import FRAME_SHAPE, N_GRIP_LEVELS, N_PATTERNS, patterns_of
from common.tactile.synthetic import GeneratorParams, SyntheticTactileModel
from robot_side.perception.errors import DatasetError

log = logging.getLogger(__name__)

PAPER_SIZE = 13_392  # pairs in the paper's data set: 12 patterns x 31 levels x 36


@dataclass
class RandomizationRanges:
    """(low, high) of each generator parameter drawn per simulated sensor.

    The ranges bracket the defaults (GeneratorParams) by what differs between
    real pipettes, pads and boards. The robustness sets in the training
    report lie outside them on purpose (more noise, a wider pipette, more
    dead taxels), so they measure generalisation, not memory.
    """

    cover_blur_mm: tuple[float, float] = param((0.3, 1.0), "soft to stiff pad covers")
    side_offset_mm: tuple[float, float] = param(
        (3.8, 8.0), "'left' grasps land 1.5 to 3 taxels off centre (4.2 mm: 6 mm along a row at 45)"
    )
    angle_jitter_deg: tuple[float, float] = param((2.0, 7.0), "careful to sloppy grasps")
    offset_jitter_mm: tuple[float, float] = param((0.5, 1.5), "careful to sloppy grasps")
    pipette_diameter_mm: tuple[float, float] = param(
        (4.0, 7.5), "Pasteur pipette stems vary by maker and by where they are held"
    )
    width_min_fraction: tuple[float, float] = param((0.08, 0.3), "stiffer or softer LDPE")
    width_max_fraction: tuple[float, float] = param(
        (0.6, 1.4), "how far the top level squashes: a flat tube's contact nears pi/2 x diameter"
    )
    line_load_min_n_per_mm: tuple[float, float] = param(
        (0.6, 1.6), "the lightest level from patchy (below the floor between rows) to clear"
    )
    line_load_max_n_per_mm: tuple[float, float] = param(
        (4.0, 10.0), "grippers and force settings differ in their strongest squeeze"
    )
    edge_loading_max: tuple[float, float] = param((0.0, 0.8), "solid-like to hollow-like tubes")
    along_band_ripple: tuple[float, float] = param((0.0, 0.3), "uniform to uneven tubes")
    along_band_gradient: tuple[float, float] = param((0.0, 0.4), "parallel to skewed pads")
    bend_max_mm: tuple[float, float] = param((0.0, 1.2), "straight to bowed tubes")
    tip_on_pad_probability: tuple[float, float] = param((0.0, 0.1), "grasps near the tip")
    pad_gain_mismatch: tuple[float, float] = param((0.0, 0.2), "matched to poorly matched pads")
    pad_misregistration_mm: tuple[float, float] = param((0.0, 0.8), "mounting tolerance")
    pad_balance_jitter: tuple[float, float] = param((0.0, 0.15), "stiff to flexing fingers")
    gain_spread: tuple[float, float] = param((0.02, 0.15), "fresh to aged calibration")
    zero_offset_n: tuple[float, float] = param((0.0, 0.15), "tare residuals")
    noise_n: tuple[float, float] = param((0.02, 0.25), "quiet to noisy boards")
    noise_relative: tuple[float, float] = param((0.0, 0.05), "load-dependent noise")
    dead_taxel_fraction: tuple[float, float] = param((0.0, 0.04), "new to worn pads")
    stuck_taxel_fraction: tuple[float, float] = param((0.0, 0.01), "new to worn pads")

    def draw(self, base: GeneratorParams, rng: np.random.Generator) -> GeneratorParams:
        """``base`` with every ranged field drawn uniformly from its range."""
        values = {}
        for f in dataclasses.fields(self):
            lo, hi = getattr(self, f.name)
            values[f.name] = float(rng.uniform(lo, hi)) if hi > lo else float(lo)
        return dataclasses.replace(base, **values)


@dataclass
class DatasetConfig:
    repeats: int = param(
        108, "frames per (pattern, grip level): 40,176 pairs, 3x the paper's 13,392 (36)"
    )
    frames_per_sensor: int = param(
        48, "frames from one simulated sensor before a new one (defects, settings) is drawn"
    )
    randomize: bool = param(True, "draw each sensor's settings from [ranges] (else: [generator])")
    seed: int = param(0, "seeds everything: same seed, same data set")
    generator: GeneratorParams = param(GeneratorParams(), "the base generator settings")
    ranges: RandomizationRanges = param(RandomizationRanges(), "domain randomisation ranges")

    def __post_init__(self) -> None:
        if self.repeats < 1:
            raise ValueError("repeats must be at least 1")
        if self.frames_per_sensor < 1:
            raise ValueError("frames_per_sensor must be at least 1")


@dataclass
class TactileDataset:
    """Frames and labels in memory; ``grip_level`` 0 means unknown."""

    frames: np.ndarray  # float32 (N, 2, 10, 10)
    angle: np.ndarray  # int64 (N,)
    position: np.ndarray  # int64 (N,)
    grip_level: np.ndarray  # int64 (N,)
    sensor: np.ndarray  # int64 (N,)
    meta: dict[str, Any] = dataclasses.field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def pattern(self) -> np.ndarray:
        return patterns_of(self.angle, self.position)

    def subset(self, index: np.ndarray) -> TactileDataset:
        return TactileDataset(
            self.frames[index],
            self.angle[index],
            self.position[index],
            self.grip_level[index],
            self.sensor[index],
            dict(self.meta),
        )

    def save(self, path: str | Path) -> Path:
        """Write the documented ``.npz`` layout (uncompressed: it loads fastest)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        meta = np.frombuffer(json.dumps(self.meta).encode(), dtype=np.uint8)
        with path.open("wb") as f:
            np.savez(
                f,
                frames=self.frames.astype(np.float32, copy=False),
                angle=self.angle.astype(np.int64, copy=False),
                position=self.position.astype(np.int64, copy=False),
                grip_level=self.grip_level.astype(np.int64, copy=False),
                sensor=self.sensor.astype(np.int64, copy=False),
                meta=meta,
            )
        return path


def generate(
    config: DatasetConfig | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> TactileDataset:
    """A balanced synthetic set: every (pattern, grip level) ``repeats`` times.

    The (pattern, level) pairs are shuffled, then cut into sessions of
    ``frames_per_sensor``; each session is one simulated sensor. Everything is
    drawn from ``config.seed``, so the same config gives the same bytes.
    """
    config = config or DatasetConfig()
    rng = np.random.default_rng(config.seed)
    patterns, levels = np.meshgrid(np.arange(N_PATTERNS), np.arange(1, N_GRIP_LEVELS + 1))
    pairs = np.stack([patterns.ravel(), levels.ravel()], axis=1)
    pairs = np.repeat(pairs, config.repeats, axis=0)
    pairs = pairs[rng.permutation(len(pairs))]
    n = len(pairs)
    frames = np.empty((n, *FRAME_SHAPE), dtype=np.float32)
    sensor = np.empty(n, dtype=np.int64)
    model = None
    for i, (pattern, level) in enumerate(pairs):
        if i % config.frames_per_sensor == 0:
            session = i // config.frames_per_sensor
            params = (
                config.ranges.draw(config.generator, rng) if config.randomize else config.generator
            )
            model = SyntheticTactileModel(params, seed=int(rng.integers(2**31)))
            if progress is not None:
                progress(i, n)
        sensor[i] = session
        frames[i] = model.frame(int(pattern), int(level), rng)
    if progress is not None:
        progress(n, n)
    meta = {"source": "synthetic", "config": to_dict(config)}
    return TactileDataset(
        frames=frames,
        angle=(pairs[:, 0] // 3).astype(np.int64),
        position=(pairs[:, 0] % 3).astype(np.int64),
        grip_level=pairs[:, 1].astype(np.int64),
        sensor=sensor,
        meta=meta,
    )


def generate_with(
    params: GeneratorParams, repeats: int, seed: int, frames_per_sensor: int = 48
) -> TactileDataset:
    """A set from fixed generator settings (no randomisation): robustness checks."""
    return generate(
        DatasetConfig(
            repeats=repeats,
            frames_per_sensor=frames_per_sensor,
            randomize=False,
            seed=seed,
            generator=params,
        )
    )


def load(path: str | Path, labels: str = "truth") -> TactileDataset:
    """Read a data set: the documented ``.npz``, or a folder ``deepxpalm export`` wrote."""
    path = Path(path)
    if (path / "meta" / "info.json").is_file():
        return load_lerobot(path, labels)
    if not path.is_file():
        raise DatasetError(f"data set {path} does not exist")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile) as e:
        raise DatasetError(f"data set {path} is not a readable .npz: {e}") from None
    return from_arrays(arrays, where=str(path))


#: which per-row column of an exported dataset gives each kind of label
LEROBOT_LABELS = {
    "truth": "annotation.sim_truth_pattern",
    "recognised": "observation.perception.pattern",
}


def load_lerobot(root: Path, labels: str = "truth") -> TactileDataset:
    """Frames and pattern labels from a LeRobot dataset made by ``deepxpalm export``.

    ``labels="truth"`` uses the simulator's true pattern (sessions on
    simulated pads); ``"recognised"`` the pattern the robot's classifier
    sent, which only teaches a model the old model's answers (and its
    mistakes): use it to adapt to a new sensor, knowingly. Rows without a
    label (-1: no contact, or no truth on real pads) are left out; rows
    that repeat the previous row's frame (the frame was held) are left out,
    so each frame counts once.
    """
    try:
        import pyarrow.parquet as pq
    except ImportError:
        raise DatasetError(
            f"{root} is a LeRobot dataset: reading it needs pyarrow (pip install '.[dataset]')"
        ) from None
    if labels not in LEROBOT_LABELS:
        raise DatasetError(f"labels must be one of {sorted(LEROBOT_LABELS)}, not {labels!r}")
    column = LEROBOT_LABELS[labels]
    frame_columns = ["observation.tactile.frames", "observation.tactile.frame_seq"]
    wanted = [*frame_columns, "episode_index", column]
    frames, pattern, sensor = [], [], []
    files = sorted((root / "data").glob("chunk-*/file-*.parquet"))
    if not files:
        raise DatasetError(f"{root} has no data/chunk-*/file-*.parquet")
    last_seq = None
    for f in files:
        table = pq.read_table(f, columns=wanted)
        seq = table.column("observation.tactile.frame_seq").to_numpy()
        label = table.column(column).to_numpy()
        keep = label >= 0
        repeat = np.concatenate([[seq[0] == last_seq], seq[1:] == seq[:-1]]) if len(seq) else seq
        keep &= ~repeat
        last_seq = seq[-1] if len(seq) else last_seq
        flat = table.column("observation.tactile.frames").combine_chunks().flatten().flatten()
        values = flat.flatten().to_numpy().reshape(-1, 2, 10, 10)
        frames.append(values[keep])
        pattern.append(label[keep])
        sensor.append(table.column("episode_index").to_numpy()[keep])
    arrays = {
        "frames": np.concatenate(frames),
        "pattern": np.concatenate(pattern).astype(np.int64),
        "sensor": np.concatenate(sensor).astype(np.int64),
    }
    if len(arrays["frames"]) == 0:
        raise DatasetError(f"{root}: no row has a {labels} label ({column} is -1 everywhere)")
    data = from_arrays(arrays, where=str(root))
    data.meta = {"source": "lerobot", "path": str(root), "labels": column}
    return data


def from_arrays(arrays: Mapping[str, np.ndarray], where: str = "data set") -> TactileDataset:
    """Validate and convert arrays with the documented keys."""
    if "frames" not in arrays:
        raise DatasetError(f"{where} has no 'frames' array; keys are {sorted(arrays)}")
    frames = np.asarray(arrays["frames"])
    if frames.ndim != 4 or frames.shape[1:] != FRAME_SHAPE:
        raise DatasetError(f"{where}: frames must have shape (N, 2, 10, 10), not {frames.shape}")
    if not np.issubdtype(frames.dtype, np.floating):
        raise DatasetError(f"{where}: frames must be floating-point newtons, not {frames.dtype}")
    frames = frames.astype(np.float32, copy=False)
    if not np.isfinite(frames).all():
        raise DatasetError(f"{where}: frames contain NaN or infinite values")
    n = len(frames)
    if "angle" in arrays and "position" in arrays:
        angle = _labels(arrays["angle"], n, 4, "angle", where)
        position = _labels(arrays["position"], n, 3, "position", where)
    elif "pattern" in arrays:
        pattern = _labels(arrays["pattern"], n, N_PATTERNS, "pattern", where)
        angle, position = pattern // 3, pattern % 3
    else:
        raise DatasetError(f"{where} needs 'angle' and 'position' arrays, or a 'pattern' array")
    if "grip_level" in arrays:
        grip = _labels(arrays["grip_level"], n, N_GRIP_LEVELS + 1, "grip_level", where)
    else:
        grip = np.zeros(n, dtype=np.int64)
    sensor = (
        np.asarray(arrays["sensor"]).astype(np.int64)
        if "sensor" in arrays
        else np.zeros(n, dtype=np.int64)
    )
    if sensor.shape != (n,):
        raise DatasetError(f"{where}: sensor must have shape ({n},), not {sensor.shape}")
    meta: dict[str, Any] = {}
    if "meta" in arrays:
        try:
            meta = json.loads(np.asarray(arrays["meta"]).tobytes().decode())
        except (UnicodeDecodeError, json.JSONDecodeError):
            log.warning("%s: ignoring a meta entry that is not JSON", where)
    return TactileDataset(frames, angle, position, grip, sensor, meta)


def _labels(values: np.ndarray, n: int, n_classes: int, name: str, where: str) -> np.ndarray:
    values = np.asarray(values)
    if values.shape != (n,):
        raise DatasetError(f"{where}: {name} must have shape ({n},), not {values.shape}")
    if not np.issubdtype(values.dtype, np.integer):
        raise DatasetError(f"{where}: {name} must be integers, not {values.dtype}")
    if n and (values.min() < 0 or values.max() >= n_classes):
        raise DatasetError(f"{where}: {name} must lie in 0..{n_classes - 1}")
    return values.astype(np.int64, copy=False)


def split_indices(
    n: int, seed: int = 0, fractions: tuple[float, float, float] = (0.5, 0.25, 0.25)
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Train, validation and test indices: a seeded permutation cut 50/25/25.

    The same (n, seed) always gives the same split, so the test set of a
    shipped model can be rebuilt to check its report.
    """
    if len(fractions) != 3 or min(fractions) < 0 or not np.isclose(sum(fractions), 1.0):
        raise ValueError(f"fractions must be three non-negative numbers summing to 1: {fractions}")
    order = np.random.default_rng(seed).permutation(n)
    n_train = round(fractions[0] * n)
    n_val = round(fractions[1] * n)
    return order[:n_train], order[n_train : n_train + n_val], order[n_train + n_val :]


def split(
    data: TactileDataset, seed: int = 0
) -> tuple[TactileDataset, TactileDataset, TactileDataset]:
    """(train, validation, test) of ``data`` by ``split_indices``."""
    train, val, test = split_indices(len(data), seed)
    return data.subset(train), data.subset(val), data.subset(test)
