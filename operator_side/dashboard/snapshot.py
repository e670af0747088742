"""What the live views show of the operator node: one copy, safe to read from another thread.

The dashboard, the demo's terminal view and the status file read a
``Snapshot``; the node takes one (``operator_side.node.snapshot``), so the
views need nothing of the node but this.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass
class Snapshot:
    """What the live views show; a copy, safe to read from another thread."""

    link_state: str
    stimulus: np.ndarray | None
    pattern: int | None
    confidence: float | None
    grip_level: int | None
    frame: np.ndarray | None
    goal_counts: np.ndarray
    goal_angles: np.ndarray
    age_ms: float | None
    stats: dict[str, float]
    robot_stats: dict[str, float]
    #: with a signing key: who holds the robot's control lease (``OperatorNode.control_view``)
    control: dict[str, Any] | None = None

    def as_json(self) -> dict[str, Any]:
        """Plain JSON data (an operator node in another process shows it: its status file)."""
        out = dataclasses.asdict(self)
        for name in (*_SNAPSHOT_ARRAYS, "goal_angles"):
            value = out[name]
            out[name] = None if value is None else np.asarray(value).tolist()
        return json.loads(json.dumps(out, default=_plain))

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Snapshot:
        fields = dict(data)
        for name, dtype in _SNAPSHOT_ARRAYS.items():
            if fields[name] is not None:
                fields[name] = np.array(fields[name], dtype=dtype)
        fields["goal_angles"] = np.array(fields["goal_angles"], dtype=np.float64)
        return cls(**fields)


_SNAPSHOT_ARRAYS = {"stimulus": np.float32, "frame": np.float32, "goal_counts": np.int64}


def _plain(value: Any) -> Any:
    """A NumPy scalar or bytes (a key) as JSON."""
    if isinstance(value, bytes):
        return value.hex()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"{type(value).__name__} is not JSON")
