"""Data set generation, the file format, the loader and the 50/25/25 split."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from robot_side.perception import DatasetError
from robot_side.perception import dataset as ds


@pytest.fixture(scope="module")
def small() -> ds.TactileDataset:
    return ds.generate(ds.DatasetConfig(repeats=1, frames_per_sensor=20, seed=3))


def test_default_size_is_at_least_the_papers() -> None:
    config = ds.DatasetConfig()
    assert config.repeats * 12 * 31 >= ds.PAPER_SIZE


def test_every_pattern_and_grip_level_appears_repeats_times(small: ds.TactileDataset) -> None:
    assert len(small) == 12 * 31
    pairs = set(zip(small.pattern.tolist(), small.grip_level.tolist(), strict=True))
    assert pairs == {(p, g) for p in range(12) for g in range(1, 32)}
    assert small.frames.dtype == np.float32 and small.frames.shape == (372, 2, 10, 10)
    # sessions of 20 frames, each a new simulated sensor
    assert small.sensor.max() == (372 - 1) // 20


@pytest.mark.slow
@pytest.mark.untimed  # no timing checked
def test_generation_is_reproducible_by_seed(small: ds.TactileDataset) -> None:
    again = ds.generate(ds.DatasetConfig(repeats=1, frames_per_sensor=20, seed=3))
    assert np.array_equal(again.frames, small.frames)
    other = ds.generate(ds.DatasetConfig(repeats=1, frames_per_sensor=20, seed=4))
    assert not np.array_equal(other.frames, small.frames)


def test_save_and_load_round_trip(small: ds.TactileDataset, tmp_path: Path) -> None:
    path = small.save(tmp_path / "set.npz")
    back = ds.load(path)
    for key in ("frames", "angle", "position", "grip_level", "sensor"):
        assert np.array_equal(getattr(back, key), getattr(small, key)), key
    assert back.meta["source"] == "synthetic"
    assert back.meta["config"]["seed"] == 3


def test_recorded_frames_with_patterns_and_no_grip_levels_load(tmp_path: Path) -> None:
    frames = np.random.default_rng(0).uniform(0, 9, (5, 2, 10, 10))  # float64 is fine
    np.savez(tmp_path / "lab.npz", frames=frames, pattern=np.array([0, 4, 5, 11, 7]))
    data = ds.load(tmp_path / "lab.npz")
    assert data.frames.dtype == np.float32
    assert data.angle.tolist() == [0, 1, 1, 3, 2]
    assert data.position.tolist() == [0, 1, 2, 2, 1]
    assert data.grip_level.tolist() == [0] * 5


@pytest.mark.parametrize(
    ("arrays", "message"),
    [
        ({"angle": np.zeros(2, int), "position": np.zeros(2, int)}, "no 'frames'"),
        ({"frames": np.zeros((2, 10, 10, 2)), "pattern": np.zeros(2, int)}, "shape"),
        ({"frames": np.zeros((2, 2, 10, 10))}, "needs 'angle'"),
        ({"frames": np.zeros((2, 2, 10, 10)), "pattern": np.array([0, 12])}, "0..11"),
        ({"frames": np.zeros((2, 2, 10, 10)), "pattern": np.array([0.0, 1.0])}, "integers"),
        ({"frames": np.full((1, 2, 10, 10), np.nan), "pattern": np.array([0])}, "NaN"),
    ],
)
def test_malformed_files_are_refused_with_the_reason(
    arrays: dict, message: str, tmp_path: Path
) -> None:
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(DatasetError, match=message):
        ds.load(tmp_path / "bad.npz")


def test_missing_or_unreadable_files_are_refused(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="does not exist"):
        ds.load(tmp_path / "none.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(DatasetError, match="readable"):
        ds.load(tmp_path / "junk.npz")


@pytest.mark.slow
@pytest.mark.untimed  # no timing checked
@given(n=st.integers(0, 5000), seed=st.integers(0, 2**32 - 1))
def test_split_is_a_fixed_50_25_25_partition(n: int, seed: int) -> None:
    train, val, test = ds.split_indices(n, seed)
    assert len(train) == round(n / 2) and len(val) == round(n / 4)
    both = np.concatenate([train, val, test])
    assert np.array_equal(np.sort(both), np.arange(n))
    again = ds.split_indices(n, seed)
    assert all(np.array_equal(a, b) for a, b in zip(again, (train, val, test), strict=True))


def test_split_of_a_data_set_keeps_labels_with_frames(small: ds.TactileDataset) -> None:
    train, val, test = ds.split(small, seed=0)
    assert len(train) + len(val) + len(test) == len(small)
    idx, _, _ = ds.split_indices(len(small), 0)
    assert np.array_equal(train.frames, small.frames[idx])
    assert np.array_equal(train.pattern, small.pattern[idx])


def test_randomisation_ranges_draw_within_bounds() -> None:
    ranges = ds.RandomizationRanges()
    rng = np.random.default_rng(0)
    for _ in range(20):
        p = ranges.draw(ds.GeneratorParams(), rng)
        assert ranges.noise_n[0] <= p.noise_n <= ranges.noise_n[1]
        assert (
            ranges.pipette_diameter_mm[0] <= p.pipette_diameter_mm <= ranges.pipette_diameter_mm[1]
        )
