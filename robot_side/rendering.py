"""From a tactile frame to the 3x3 stimulus: ``common.stimulus``, and the rule for one frame.

``render_frame`` is that rule (mode -> pattern -> nothing pressed or the
rendered cells): the robot node, replay and the bench all call it, so they
cannot disagree on a frame.

The rendering is NumPy only and lives in ``common`` so the operator's study
renders exactly as the robot does without importing the robot side; the
robot's modules keep importing it from here.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np

from common.stimulus import (
    CONTACT_THRESHOLD_N,
    METHODS,
    NO_CELLS,
    ORDERS,
    SENSOR_MAX_N,
    Method,
    Order,
    antialiased_bicubic_weights,
    area_weights,
    downsizing_matrix,
    downsizing_weights,
    is_contact,
    mask_columns,
    plain_bicubic_weights,
    render_cells,
    render_contact,
    render_stimulus,
    sanitize_frame,
    sanitize_with_peak,
)

__all__ = [
    "CONTACT_THRESHOLD_N",
    "METHODS",
    "NO_CELLS",
    "ORDERS",
    "SENSOR_MAX_N",
    "Method",
    "Order",
    "RenderSettings",
    "antialiased_bicubic_weights",
    "area_weights",
    "downsizing_matrix",
    "downsizing_weights",
    "is_contact",
    "mask_columns",
    "plain_bicubic_weights",
    "render_cells",
    "render_contact",
    "render_frame",
    "render_stimulus",
    "sanitize_frame",
    "sanitize_with_peak",
]


class RenderSettings(Protocol):
    """What ``render_frame`` reads of ``robot_side.config.RenderConfig``."""

    mode: str
    method: Method
    order: Order


def render_frame(
    frame: np.ndarray,
    contact: bool,
    render: RenderSettings,
    *,
    classify: Callable[[np.ndarray], int] | None = None,
    truth: int | None = None,
) -> tuple[list[float], int | None]:
    """The rule for one frame: (the nine cells sent, the pattern they were rendered with).

    ``frame`` is sanitized and ``contact`` its contact test. Without contact
    nothing is pressed and nothing is classified. The mode picks the mask:
    ``mask`` the classifier's (``classify`` is called only then),
    ``mask_ground_truth`` the simulator's ``truth``, ``direct`` none. A mask
    mode without a pattern (nothing held) presses nothing.
    """
    if not contact:
        return list(NO_CELLS), None
    mode = render.mode
    if mode == "direct":
        pattern = None
    else:
        pattern = classify(frame) if mode == "mask" else truth
        if pattern is None:
            return list(NO_CELLS), None
    return render_cells(frame, pattern, method=render.method, order=render.order), pattern
