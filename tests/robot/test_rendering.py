"""Rendering follows the tactile convention: contact map, bicubic 3x3, peak per row, mask."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from common.tactile.contract import MASKS, matches_pattern
from common.tactile.stimulus import (
    antialiased_bicubic_weights,
    area_weights,
    plain_bicubic_weights,
    render_stimulus,
)
from harness.bench.downsizing import downsize, peak_per_row


def band_frame(cells: list[tuple[int, int]], force: float = 6.0) -> np.ndarray:
    frame = np.zeros((2, 10, 10), np.float32)
    for r, c in cells:
        frame[:, r, c] = force
    return frame


def test_weights_are_normalised():
    for w in (
        antialiased_bicubic_weights(10, 3),
        plain_bicubic_weights(10, 3),
        area_weights(10, 3),
    ):
        np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-12)


def test_antialiased_sees_a_band_that_plain_bicubic_misses():
    # A thin vertical band on column 3 lies between plain bicubic's sample points,
    # where its weights are negative: it vanishes. Antialiased bicubic feels it.
    frame = band_frame([(r, 3) for r in range(10)])
    assert not render_stimulus(frame, None, method="plain").any()
    direct = render_stimulus(frame, None, method="antialiased")
    assert (direct.max(axis=1) > 0.5).all()


@pytest.mark.slow
def test_matches_torch_antialiased_bicubic():
    torch = pytest.importorskip("torch")
    rng = np.random.default_rng(0)
    for _ in range(20):
        x = rng.uniform(0, 9, (10, 10)).astype(np.float32)
        t = torch.from_numpy(x)[None, None]
        ref = torch.nn.functional.interpolate(t, size=(3, 3), mode="bicubic", antialias=True)
        np.testing.assert_allclose(
            antialiased_bicubic_weights(10, 3) @ x @ antialiased_bicubic_weights(10, 3).T,
            ref[0, 0].numpy(),
            atol=1e-5,
        )
        ref = torch.nn.functional.interpolate(t, size=(3, 3), mode="bicubic", align_corners=False)
        w = plain_bicubic_weights(10, 3)
        np.testing.assert_allclose(w @ x @ w.T, ref[0, 0].numpy(), atol=1e-5)


def test_vertical_band_in_centre_renders_the_90_deg_centre_pattern():
    frame = band_frame([(r, c) for r in range(10) for c in (4, 5)])
    stim = render_stimulus(frame, 6)
    assert matches_pattern(stim, 6)
    assert render_stimulus(frame, None)[:, 1].min() > 0  # direct rendering finds it too


def test_mask_keeps_at_most_one_cell_per_row_and_only_mask_cells():
    rng = np.random.default_rng(1)
    for p in range(12):
        stim = render_stimulus(rng.uniform(0, 9, (2, 10, 10)).astype(np.float32), p)
        assert ((stim > 0).sum(axis=1) <= 1).all()
        assert not (stim > 0)[~MASKS[p]].any()


def test_no_contact_is_all_zero():
    frame = np.full((2, 10, 10), 0.99, np.float32)
    assert not render_stimulus(frame, 3).any()
    assert not render_stimulus(frame, None).any()


def test_peak_ties_go_to_lowest_column():
    x = np.array([[1, 1, 0], [0, 2, 2], [0, 0, 0]], np.float32)
    np.testing.assert_array_equal(peak_per_row(x), [[1, 0, 0], [0, 2, 0], [0, 0, 0]])


def test_mask_then_peak_option_recovers_a_row_the_paper_order_loses():
    # Row 1's peak lies in column 2 but pattern 4's mask wants (1, 0).
    frame = np.zeros((2, 10, 10), np.float32)
    frame[:, 4:6, 0:2] = 3.0
    frame[:, 4:6, 8:10] = 8.0
    assert render_stimulus(frame, 4, order="peak_then_mask")[1].sum() == 0
    assert render_stimulus(frame, 4, order="mask_then_peak")[1, 0] > 0


frames = hnp.arrays(
    np.float32,
    (2, 10, 10),
    elements=st.one_of(
        st.floats(-20, 20, width=32), st.floats(width=32), st.sampled_from([0.0, 1.0, 9.0, 3e38])
    ),
)


@given(
    frames,
    st.one_of(st.none(), st.integers(0, 11)),
    st.sampled_from(["antialiased", "plain", "area"]),
)
@pytest.mark.slow
def test_any_frame_gives_a_finite_non_negative_bounded_stimulus(frame, pattern, method):
    stim = render_stimulus(frame, pattern, method=method)
    assert stim.shape == (3, 3) and stim.dtype == np.float32
    assert np.isfinite(stim).all()
    assert stim.min() >= 0 and stim.max() <= 9.0
    assert ((stim > 0).sum(axis=1) <= 1).all()


@pytest.mark.slow
@given(hnp.arrays(np.float32, (10, 10), elements=st.floats(0, 9, width=32)))
def test_cubic_overshoot_never_goes_negative(x):
    out = downsize(x)
    assert out.min() >= 0 and out.max() <= 9.0


@pytest.mark.slow
@pytest.mark.parametrize("method", ["antialiased", "plain", "area"])
@pytest.mark.parametrize("order", ["mask_then_peak", "peak_then_mask"])
def test_the_fused_path_renders_what_the_separable_oracle_renders(method, order):
    """One (9, 200) product per frame against contact map, ``Wy @ X @ Wx.T``, peak, mask."""
    from common.tactile.stimulus import render_cells, sanitize_frame
    from harness.bench.downsizing import separable_stimulus

    rng = np.random.default_rng(7)
    for _ in range(50):
        frame = sanitize_frame(rng.uniform(0, 9, (2, 10, 10)).astype(np.float32))
        for pattern in (None, *range(len(MASKS))):
            got = np.array(render_cells(frame, pattern, method=method, order=order), np.float32)
            want = separable_stimulus(frame, pattern, order, method)
            np.testing.assert_allclose(got.reshape(3, 3), want, atol=2e-6)
