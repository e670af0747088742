"""The lab's ground truth: the pattern a grasped pipette makes on the pads, from the engine.

The pressed pipette's axis and top are projected into the pads' plane (the
tool's x-z plane, columns along +x, rows up along +z): its tilt gives the
angle class, its offset from the pad centre across the axis the position
class (docs/tactile.md).
"""

from __future__ import annotations

import math

import numpy as np

from common.tactile.contract import N_ANGLES, pattern_of
from common.tactile.synthetic import offset_direction
from robot_side.lab.model import PAD_CENTRE_Z_M
from robot_side.lab.world import LabWorld

#: a band this far (mm) from the pad centre, across its axis, is "left"/"right" (or up/down)
SIDE_THRESHOLD_MM = 3.0


def grasp_geometry(world: LabWorld, pipette: int) -> tuple[float, float]:
    """(tilt deg in 0..180, offset mm along class 1's direction) of a pipette on the pads."""
    t = world.flange()
    p = world.pipettes[pipette]
    rot = t[:3, :3]
    axis = rot.T @ p.axis
    top = rot.T @ (world.pipette_top(pipette) - t[:3, 3])
    u = np.array([axis[0], axis[2]])
    u /= max(float(np.linalg.norm(u)), 1e-9)
    theta = math.degrees(math.atan2(u[1], u[0])) % 180.0
    rel = np.array([top[0], top[2] - PAD_CENTRE_Z_M])
    w = rel - float(rel @ u) * u  # pad centre -> the axis line, across it
    angle_class = round(theta / 45.0) % N_ANGLES
    dx, dy = offset_direction(angle_class)
    return theta, float(w[0] * dx + w[1] * dy) * 1000.0


def grasp_pattern(world: LabWorld) -> int | None:
    """The tactile contract's pattern being felt, or None."""
    i = world.touching_pipette()
    if i is None:
        return None
    theta, offset_mm = grasp_geometry(world, i)
    angle_class = round(theta / 45.0) % N_ANGLES
    if offset_mm > SIDE_THRESHOLD_MM:
        position = 1
    elif offset_mm < -SIDE_THRESHOLD_MM:
        position = 2
    else:
        position = 0
    return pattern_of(angle_class, position)
