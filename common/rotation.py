"""Rotation vectors (the UR's axis-angle pose convention) to matrices and back.

NumPy only: the robot's arm simulator and the operator's scripted hands both
read and write UR poses ``[x, y, z, rx, ry, rz]``.

Both directions go through the unit quaternion, with no threshold between
branches: the matrix is read by Shepperd's method (the quaternion component
of largest magnitude is taken from the diagonal, the others from it), and the
angle by ``2 atan2(|v|, w)``, which keeps its absolute error near machine
epsilon at every angle. The UR's tool-down pose sits at a magnitude of
exactly pi, where ``acos`` of the trace and a skew-part formula lose digits:
the earlier version switched branches at ``pi - theta < 1e-6`` and lost 5e-7
rad just outside it.
"""

from __future__ import annotations

import math

import numpy as np


def rotvec_to_quaternion(r: np.ndarray) -> np.ndarray:
    """``[w, x, y, z]`` with ``w >= 0`` for ``|r| <= pi``."""
    r = np.asarray(r, dtype=float)
    theta = math.sqrt(float(r @ r))
    half = 0.5 * theta
    # sin(theta/2)/theta, its limit 1/2 at zero: no division by a vanishing angle
    scale = math.sin(half) / theta if theta > 1e-8 else 0.5 - theta * theta / 48.0
    return np.array([math.cos(half), *(scale * r)])


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q / math.sqrt(float(q @ q))
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quaternion(m: np.ndarray) -> np.ndarray:
    """Shepperd's method: ``[w, x, y, z]``, unit, with ``w >= 0``."""
    m = np.asarray(m, dtype=float)
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    # the skew part (4 w q_i) and the symmetric part (4 q_i q_j) off the diagonal
    dx, dy, dz = m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]
    sxy, sxz, syz = m[0, 1] + m[1, 0], m[0, 2] + m[2, 0], m[1, 2] + m[2, 1]
    # 4 q_i^2 - 1 for w, x, y, z: the square root of the largest, the others divided by it
    candidates = (trace, m[0, 0], m[1, 1], m[2, 2])
    i = max(range(4), key=candidates.__getitem__)
    if i == 0:
        s = 2.0 * math.sqrt(max(1.0 + trace, 0.0))
        q = np.array([s / 4, dx / s, dy / s, dz / s])
    elif i == 1:
        s = 2.0 * math.sqrt(max(1.0 + 2.0 * m[0, 0] - trace, 0.0))
        q = np.array([dx / s, s / 4, sxy / s, sxz / s])
    elif i == 2:
        s = 2.0 * math.sqrt(max(1.0 + 2.0 * m[1, 1] - trace, 0.0))
        q = np.array([dy / s, sxy / s, s / 4, syz / s])
    else:
        s = 2.0 * math.sqrt(max(1.0 + 2.0 * m[2, 2] - trace, 0.0))
        q = np.array([dz / s, sxz / s, syz / s, s / 4])
    q /= math.sqrt(float(q @ q))
    return q if q[0] >= 0 else -q


def quaternion_to_rotvec(q: np.ndarray) -> np.ndarray:
    """The rotation vector of magnitude in [0, pi] (at exactly pi, either sign is the same turn)."""
    w, v = float(q[0]), np.asarray(q[1:], dtype=float)
    if w < 0:
        w, v = -w, -v
    sin_half = math.sqrt(float(v @ v))
    theta = 2.0 * math.atan2(sin_half, w)
    # theta / sin(theta/2), its limit 2 at zero
    scale = theta / sin_half if sin_half > 1e-8 else 2.0 + sin_half * sin_half / 3.0
    return scale * v


def rotvec_to_matrix(r: np.ndarray) -> np.ndarray:
    return quaternion_to_matrix(rotvec_to_quaternion(r))


def matrix_to_rotvec(m: np.ndarray) -> np.ndarray:
    return quaternion_to_rotvec(matrix_to_quaternion(m))


def rotation_angle(a: np.ndarray, b: np.ndarray) -> float:
    """The angle (rad, 0..pi) of the turn between two rotation matrices, accurate at 0 and pi."""
    return float(np.linalg.norm(matrix_to_rotvec(b @ np.asarray(a).T)))
