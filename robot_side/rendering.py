"""From a tactile frame to the 3x3 stimulus: the robot node's name for ``common.stimulus``.

The rendering is NumPy only and lives in ``common`` so the operator's study
renders exactly as the robot does without importing the robot side; the
robot's modules keep importing it from here.
"""

from __future__ import annotations

from common.stimulus import (
    _WEIGHTS,  # the downsizing bench compares the weight variants directly
    CONTACT_THRESHOLD_N,
    METHODS,
    ORDERS,
    SENSOR_MAX_N,
    Method,
    Order,
    antialiased_bicubic_weights,
    area_weights,
    contact_map,
    downsize,
    downsizing_matrix,
    is_contact,
    mask_columns,
    peak_per_row,
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
    "ORDERS",
    "SENSOR_MAX_N",
    "_WEIGHTS",
    "Method",
    "Order",
    "antialiased_bicubic_weights",
    "area_weights",
    "contact_map",
    "downsize",
    "downsizing_matrix",
    "is_contact",
    "mask_columns",
    "peak_per_row",
    "plain_bicubic_weights",
    "render_cells",
    "render_contact",
    "render_stimulus",
    "sanitize_frame",
    "sanitize_with_peak",
]
