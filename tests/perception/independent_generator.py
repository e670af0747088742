"""A second, deliberately simple frame generator written from the tactile contract alone.

It shares no code with common.tactile.synthetic: bands are sampled at
taxel centres (no area integration), profiles are Gaussian or flat-topped,
the side offset may be taken perpendicular to the band or straight along
the rows/columns, and pad 2 is pad 1 with its own gain and noise. A model
that only learned the synthetic generator's quirks fails here; the shipped
model must not.
"""

from __future__ import annotations

import math

import numpy as np

PITCH_MM = 2.41


def spec_frame(pattern: int, grip_level: int, rng: np.random.Generator) -> np.ndarray:
    angle_class, position_class = divmod(pattern, 3)
    theta = math.radians(45.0 * angle_class + rng.normal(0.0, 2.0))
    ux, uy = math.cos(theta), math.sin(theta)
    nx, ny = -uy, ux
    side = (0.0, 1.0, -1.0)[position_class]
    shift = side * rng.normal(6.0, 0.5) + rng.normal(0.0, 0.5) * (side == 0)
    if angle_class == 0:
        cx, cy = 0.0, shift  # up is towards row 0 (+y)
    elif rng.random() < 0.5:
        cx, cy = -shift, 0.0  # left is towards column 0, shifted along the rows
    else:
        sign = 1.0 if nx < 0 else -1.0  # perpendicular, on the left side for +shift
        cx, cy = sign * nx * shift, sign * ny * shift
    cols = (np.arange(10) - 4.5) * PITCH_MM
    rows = (4.5 - np.arange(10)) * PITCH_MM
    x, y = np.meshgrid(cols, rows)
    d = (x - cx) * nx + (y - cy) * ny
    t = (x - cx) * ux + (y - cy) * uy
    s = (grip_level - 1) / 30
    width = 2.0 + 6.0 * s
    if rng.random() < 0.5:
        profile = np.exp(-0.5 * (d / (width / 2.5)) ** 2)
    else:
        profile = (np.abs(d) <= width / 2).astype(float)
    amp = (1.6 + 7.5 * s) * rng.uniform(0.85, 1.15)
    along = 1.0 + 0.1 * np.sin(t / 6.0 + rng.uniform(0, 6.3))
    band = amp * profile * along
    frame = np.stack([band, band * rng.uniform(0.8, 1.2)])
    frame = frame + rng.normal(0.0, 0.2, frame.shape)
    defect = rng.random(frame.shape)
    frame[defect < 0.02] = 0.0
    frame[defect > 0.995] = 9.0
    frame[frame < 1.0] = 0.0
    return np.minimum(frame, 9.0).astype(np.float32)


def spec_set(repeats: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(frames, angle, position), every (pattern, grip level) ``repeats`` times."""
    rng = np.random.default_rng(seed)
    frames, angle, position = [], [], []
    for _ in range(repeats):
        for pattern in range(12):
            for level in range(1, 32):
                frames.append(spec_frame(pattern, level, rng))
                angle.append(pattern // 3)
                position.append(pattern % 3)
    return np.stack(frames), np.array(angle), np.array(position)
