"""The synthetic generator follows the tactile contract and the sensor's limits."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from common.config.typed import from_dict
from common.errors import ConfigError
from common.tactile.synthetic import (
    GeneratorParams,
    SyntheticTactileModel,
    mirror_finger2,
    offset_direction,
)

#: no jitter, no defects, no noise, identical pads: conventions show plainly
CLEAN = GeneratorParams(
    angle_jitter_deg=0.0,
    offset_jitter_mm=0.0,
    grip_jitter=0.0,
    taper_per_12mm=0.0,
    along_band_gradient=0.0,
    along_band_ripple=0.0,
    bend_max_mm=0.0,
    pad_gain_mismatch=0.0,
    pad_misregistration_mm=0.0,
    pad_rotation_deg=0.0,
    pad_balance_jitter=0.0,
    gain_spread=0.0,
    zero_offset_n=0.0,
    noise_n=0.0,
    noise_relative=0.0,
    dead_taxel_fraction=0.0,
    stuck_taxel_fraction=0.0,
)


def clean_frame(pattern: int, level: int = 16) -> np.ndarray:
    return SyntheticTactileModel(CLEAN, seed=0).frame(pattern, level, np.random.default_rng(0))


def centroid(pad: np.ndarray) -> tuple[float, float]:
    rows, cols = np.indices(pad.shape)
    w = pad / pad.sum()
    return float((rows * w).sum()), float((cols * w).sum())


def row_col_correlation(pad: np.ndarray) -> float:
    rows, cols = np.indices(pad.shape)
    w = pad.ravel() / pad.sum()
    r, c = rows.ravel(), cols.ravel()
    mr, mc = (w * r).sum(), (w * c).sum()
    cov = (w * (r - mr) * (c - mc)).sum()
    return float(cov / np.sqrt((w * (r - mr) ** 2).sum() * (w * (c - mc) ** 2).sum()))


# --- conventions --------------------------------------------------------


def test_vertical_left_band_lies_on_the_first_columns() -> None:
    pad = clean_frame(7)[0]  # 90 deg left
    assert pad[:, :4].sum() > 0.95 * pad.sum()
    assert (pad[:, :4] > 0).any(axis=1).all()  # along every row


def test_vertical_right_band_lies_on_the_last_columns() -> None:
    pad = clean_frame(8)[0]
    assert pad[:, 6:].sum() > 0.95 * pad.sum()


def test_horizontal_up_band_lies_on_the_first_rows() -> None:
    pad = clean_frame(1)[0]  # 0 deg up: towards row 0, the fingertip end
    assert pad[:4].sum() > 0.95 * pad.sum()
    assert (pad[:4] > 0).any(axis=0).all()  # across every column


def test_horizontal_down_band_lies_on_the_last_rows() -> None:
    pad = clean_frame(2)[0]
    assert pad[6:].sum() > 0.95 * pad.sum()


def test_centre_bands_pass_through_the_middle() -> None:
    for pattern in (0, 3, 6, 9):
        r, c = centroid(clean_frame(pattern)[0])
        assert abs(r - 4.5) < 0.5 and abs(c - 4.5) < 0.5, pattern


def test_45_deg_runs_lower_left_to_upper_right() -> None:
    # Rows grow downwards, so "/" means row falls as column rises.
    assert row_col_correlation(clean_frame(3)[0]) < -0.8
    assert row_col_correlation(clean_frame(9)[0]) > 0.8  # 135 deg: "\"


@pytest.mark.parametrize(
    ("pattern", "row_side", "col_side"),
    [
        (4, -1, -1),  # 45 left: towards column 0, perpendicular to "/" is up-left
        (5, +1, +1),  # 45 right: down-right
        (10, +1, -1),  # 135 left: perpendicular to "\" towards column 0 is down-left
        (11, -1, +1),  # 135 right: up-right
    ],
)
def test_diagonal_offsets_are_perpendicular_and_on_the_named_side(
    pattern: int, row_side: int, col_side: int
) -> None:
    r, c = centroid(clean_frame(pattern)[0])
    assert np.sign(r - 4.5) == row_side and np.sign(c - 4.5) == col_side
    # About 6 mm from the centre, perpendicular: 2.5 taxels.
    assert np.hypot(r - 4.5, c - 4.5) == pytest.approx(6.0 / 2.41, abs=0.5)


def test_offset_direction_of_class_1() -> None:
    assert offset_direction(0) == pytest.approx((0.0, 1.0))  # up
    assert offset_direction(2) == pytest.approx((-1.0, 0.0))  # left
    assert offset_direction(1)[0] < 0 and offset_direction(3)[0] < 0


def test_both_pads_show_the_band_on_the_same_taxels() -> None:
    for pattern in range(12):
        f = clean_frame(pattern)
        assert np.array_equal(f[0] > 0, f[1] > 0), pattern


def test_mirror_finger2_is_its_own_inverse_and_flips_only_pad_2() -> None:
    f = clean_frame(3)
    wire = mirror_finger2(f)
    assert np.array_equal(wire[0], f[0])
    assert np.array_equal(wire[1], f[1][:, ::-1])
    assert np.array_equal(mirror_finger2(wire), f)
    # On the wire, finger 2 sees the "/" band as "\".
    assert row_col_correlation(wire[1]) > 0.8
    batch = np.stack([f, f])
    assert np.array_equal(mirror_finger2(batch)[1], wire)


# --- grip levels --------------------------------------------------------


def test_band_widens_and_presses_harder_with_the_grip() -> None:
    model = SyntheticTactileModel(seed=3)
    rng = np.random.default_rng(1)
    area, force = [], []
    for level in (1, 16, 31):
        frames = np.stack([model.frame(p, level, rng) for p in range(12) for _ in range(4)])
        area.append((frames > 0).sum(axis=(1, 2, 3)).mean())
        force.append(frames.sum(axis=(1, 2, 3)).mean())
    assert area[0] < area[1] < area[2]
    assert force[0] < force[1] < force[2]


def test_lightest_grip_still_registers() -> None:
    model = SyntheticTactileModel(seed=4)
    rng = np.random.default_rng(2)
    for p in range(12):
        assert model.frame(p, 1, rng).max() >= 1.0


def test_strongest_grip_saturates_some_taxels() -> None:
    model = SyntheticTactileModel(seed=5)
    rng = np.random.default_rng(3)
    assert any((model.frame(p, 31, rng) == 9.0).any() for p in range(12))


# --- sensor limits, defects, reproducibility -----------------------------


@given(
    pattern=st.one_of(st.none(), st.integers(0, 11)),
    level=st.integers(1, 31),
    seed=st.integers(0, 2**31 - 1),
)
@pytest.mark.slow
@pytest.mark.untimed  # no timing checked
def test_every_reading_is_zero_or_within_the_sensor_range(
    pattern: int | None, level: int, seed: int
) -> None:
    f = SyntheticTactileModel(seed=seed % 50).frame(pattern, level, np.random.default_rng(seed))
    assert f.dtype == np.float32 and f.shape == (2, 10, 10)
    assert np.isfinite(f).all()
    nonzero = f[f != 0]
    assert (nonzero >= 1.0).all() and (nonzero <= 9.0).all()


def test_nothing_grasped_reads_zero_except_stuck_taxels() -> None:
    params = dataclasses.replace(GeneratorParams(), stuck_taxel_fraction=0.05)
    model = SyntheticTactileModel(params, seed=7)
    assert model.stuck_mask.any()
    f = model.frame(None, 31, np.random.default_rng(0))
    assert np.array_equal(f != 0, model.stuck_mask)
    assert np.allclose(f[model.stuck_mask], model.stuck_values_n[model.stuck_mask])


def test_dead_taxels_always_read_zero() -> None:
    params = dataclasses.replace(GeneratorParams(), dead_taxel_fraction=0.2)
    model = SyntheticTactileModel(params, seed=8)
    rng = np.random.default_rng(0)
    frames = np.stack([model.frame(p, 31, rng) for p in range(12)])
    assert (frames[:, model.dead_mask] == 0).all()


def test_same_seeds_give_the_same_frames() -> None:
    a = SyntheticTactileModel(seed=11)
    b = SyntheticTactileModel(seed=11)
    ra, rb = np.random.default_rng(5), np.random.default_rng(5)
    for p in (0, 4, 8, None):
        assert np.array_equal(a.frame(p, 20, ra), b.frame(p, 20, rb))


def test_sensor_seed_sets_the_defects() -> None:
    params = dataclasses.replace(GeneratorParams(), dead_taxel_fraction=0.1)
    a, b = SyntheticTactileModel(params, seed=1), SyntheticTactileModel(params, seed=2)
    assert not np.array_equal(a.dead_mask, b.dead_mask)
    assert not np.array_equal(a.gain, b.gain)


def test_a_held_grasp_keeps_its_band_still() -> None:
    model = SyntheticTactileModel(seed=0)
    rng = np.random.default_rng(0)
    grasp = model.draw_grasp(7, rng)
    f1 = model.contact_force(grasp, 20)
    f2 = model.contact_force(grasp, 20)
    assert np.array_equal(f1, f2)
    assert model.grasp_frame(grasp, 20, rng).shape == (2, 10, 10)


def test_invalid_arguments_are_refused() -> None:
    model = SyntheticTactileModel()
    rng = np.random.default_rng()
    with pytest.raises(ValueError, match="pattern"):
        model.frame(12, 1, rng)
    with pytest.raises(ValueError, match="grip_level"):
        model.frame(0, 0, rng)
    with pytest.raises(ValueError, match="grip_level"):
        model.frame(0, 32, rng)
    with pytest.raises(ValueError, match="noise_n"):
        GeneratorParams(noise_n=-1.0)


def test_params_load_from_a_config_table() -> None:
    params = from_dict(GeneratorParams, {"noise_n": 0.2, "pipette_diameter_mm": 7})
    assert params.noise_n == 0.2 and params.pipette_diameter_mm == 7.0
    with pytest.raises(ConfigError, match="noise"):
        from_dict(GeneratorParams, {"noise": 0.2})
    with pytest.raises(ConfigError):
        from_dict(GeneratorParams, {"noise_n": -0.2})
