"""A capture time drawn into the picture, readable after lossy video coding.

The top of the frame carries two rows of ``STAMP_BITS`` square cells: the
first row holds the capture time (wall clock, milliseconds modulo 2**32)
and an 8-bit frame counter as black and white cells, the second row holds
the same bits inverted. A reader compares the two rows cell by cell: a frame
whose rows do not disagree clearly everywhere (a half-decoded frame, a
scaled-down one) is rejected rather than misread. Cells are ``width // 40``
pixels (16 at 640 wide): big enough to survive VP8 at a few hundred kbit/s.

The browser's reader is in the dashboard's ``video.js``; this module's
``read_stamp`` is the same rule in Python, for tests and for sources that
check themselves.
"""

from __future__ import annotations

import numpy as np

STAMP_BITS = 40  # 32 bits of milliseconds, 8 bits of frame counter
MS_MODULO = 2**32


def cell_size(width: int) -> int:
    return max(4, width // STAMP_BITS)


def _bits(capture_ms: int, counter: int) -> np.ndarray:
    word = ((capture_ms % MS_MODULO) << 8) | (counter & 0xFF)
    return np.array([(word >> (STAMP_BITS - 1 - i)) & 1 for i in range(STAMP_BITS)], np.uint8)


def draw_stamp(rgb: np.ndarray, capture_ms: int, counter: int) -> None:
    """Draw the stamp in place into the top ``2 * cell_size`` rows of ``rgb``."""
    h, w, _ = rgb.shape
    c = cell_size(w)
    if 2 * c > h or STAMP_BITS * c > w:
        raise ValueError(f"a {w}x{h} frame is too small for a time stamp")
    levels = _bits(capture_ms, counter) * np.uint8(255)
    row = np.repeat(levels, c)[None, :, None]
    rgb[:c, : STAMP_BITS * c] = row
    rgb[c : 2 * c, : STAMP_BITS * c] = 255 - row
    rgb[:c, STAMP_BITS * c :] = 128
    rgb[c : 2 * c, STAMP_BITS * c :] = 128


def read_stamp(rgb: np.ndarray, margin: float = 60.0) -> tuple[int, int] | None:
    """(capture ms modulo 2**32, counter) from a decoded frame, or None when unreadable."""
    w = rgb.shape[1]
    c = cell_size(w)
    q = max(1, c // 4)  # sample each cell's centre: edges blur under coding
    grey = rgb[: 2 * c, : STAMP_BITS * c].astype(np.float32).mean(axis=2)
    cells = grey.reshape(2, c, STAMP_BITS, c)[:, q : c - q, :, q : c - q].mean(axis=(1, 3))
    diff = cells[0] - cells[1]
    if np.any(np.abs(diff) < margin):
        return None
    word = 0
    for bit in diff > 0:
        word = (word << 1) | int(bit)
    return word >> 8, word & 0xFF
