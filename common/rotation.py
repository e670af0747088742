"""Rotation vectors (the UR's axis-angle pose convention) to matrices and back.

NumPy only: the robot's arm simulator and the operator's scripted hands both
read and write UR poses ``[x, y, z, rx, ry, rz]``.
"""

from __future__ import annotations

import math

import numpy as np


def rotvec_to_matrix(r: np.ndarray) -> np.ndarray:
    theta = float(np.linalg.norm(r))
    if theta < 1e-12:
        return np.eye(3)
    k = r / theta
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(theta) * kx + (1 - math.cos(theta)) * (kx @ kx)


def matrix_to_rotvec(m: np.ndarray) -> np.ndarray:
    cos = max(-1.0, min(1.0, (np.trace(m) - 1) / 2))
    theta = math.acos(cos)
    if theta < 1e-9:
        return np.zeros(3)
    if math.pi - theta < 1e-6:
        # near 180 deg the skew part vanishes: take the axis from the diagonal
        axis = np.sqrt(np.maximum((np.diag(m) + 1) / 2, 0.0))
        i = int(np.argmax(axis))
        col = (m[:, i] + np.eye(3)[:, i]) / 2
        axis = col / np.linalg.norm(col)
        return axis * theta
    v = np.array([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]])
    return v / (2 * math.sin(theta)) * theta
