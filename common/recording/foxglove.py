"""Foxglove's message types for what the nodes record, so Foxglove shows it with no configuration.

Foxglove picks its Image and 3D panels by a channel's schema name
(``foxglove.CompressedImage``, ``foxglove.RawImage``, ``foxglove.FrameTransform``,
``foxglove.SceneUpdate``, ``foxglove.Log``). Recordings are JSON with JSON
Schema (docs/recording.md), so these are Foxglove's JSON forms: times as
``{sec, nsec}``, bytes as base64 strings. The schemas below carry the field
names and types of Foxglove's published schemas (the ``foxglove-sdk``
package's descriptors; ``tests/recording/test_foxglove.py`` compares them
field by field; ``common.recording.foxglove_schemas``); they need no Foxglove
package to write.

``views(channel, record, t_wall_ns)`` turns one recorded record into the
Foxglove messages derived from it; the recorder writes those beside the
record (docs/recording.md, "Foxglove"), and the live source serves them.
NumPy only: the operator's and the recorder's install stays light.
"""

from __future__ import annotations

import base64
import dataclasses
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from common.config.typed import param
from common.errors import ConfigError
from common.recording.foxglove_schemas import SCHEMAS as SCHEMAS  # where its readers find it
from common.rotation import rotvec_to_quaternion
from common.tactile.contract import N_PADS, PAD_COLS, PAD_ROWS, SATURATION_N

# ------------------------------------------------------------------- frames
#: the frames the 3D panel shows: the arm's base, its tool centre point, the fingers,
#: the operator's palm
BASE_FRAME = "base"
TCP_FRAME = "tcp"
FINGER_FRAMES = ("finger_1", "finger_2")
PALM_FRAME = "palm"
#: travel of each 2F-85 finger from open (position 0) to closed (255), m
FINGER_STROKE_M = 0.0425

#: recorded channel -> Foxglove type it is written as, in place (its own fields kept)
IN_PLACE: dict[str, str] = {"camera/image": "foxglove.CompressedImage"}
#: channel of the nodes' log lines
LOG_CHANNEL = "log"
#: derived topic -> its Foxglove type (every topic ``views`` can return)
VIEW_TOPICS: dict[str, str] = {
    **{f"robot/pads/{f}": "foxglove.RawImage" for f in FINGER_FRAMES},
    "robot/tf/tcp": "foxglove.FrameTransform",
    **{f"robot/tf/{f}": "foxglove.FrameTransform" for f in FINGER_FRAMES},
    "robot/palm": "foxglove.SceneUpdate",
    "operator/palm": "foxglove.SceneUpdate",
}


def stamp(t_ns: int) -> dict[str, int]:
    """Foxglove's time: whole seconds and nanoseconds (a negative time is clamped to 0)."""
    t = max(0, int(t_ns))
    return {"sec": t // 1_000_000_000, "nsec": t % 1_000_000_000}


def _vec(v: Any) -> dict[str, float]:
    return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}


_IDENTITY = {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}


def camera_fields(record: dict[str, Any], t_wall_ns: int) -> dict[str, Any]:
    """The fields a camera record adds to be a ``foxglove.CompressedImage``."""
    return {
        "timestamp": stamp(t_wall_ns),
        "frame_id": str(record.get("camera") or "camera"),
        "format": str(record.get("format") or "jpeg"),
    }


def pad_images(frame: Any, t_wall_ns: int) -> list[dict[str, Any]]:
    """Each pad as a ``foxglove.RawImage``: ``32FC1``, 0 N black to saturation white."""
    f = np.asarray(frame, dtype=np.float64).reshape(N_PADS, PAD_ROWS, PAD_COLS)
    scaled = np.clip(np.nan_to_num(f / SATURATION_N, nan=0.0, posinf=1.0), 0.0, 1.0)
    out = []
    for pad, name in zip(scaled.astype("<f4"), FINGER_FRAMES, strict=True):
        out.append(
            {
                "timestamp": stamp(t_wall_ns),
                "frame_id": name,
                "width": PAD_COLS,
                "height": PAD_ROWS,
                "encoding": "32FC1",
                "step": PAD_COLS * 4,
                "data": base64.b64encode(pad.tobytes()).decode("ascii"),
            }
        )
    return out


def tcp_transform(tcp_pose: Any, t_wall_ns: int) -> dict[str, Any]:
    """The arm's tool centre point in its base frame: UR's rotation vector as a quaternion."""
    pose = np.asarray(tcp_pose, dtype=np.float64)
    w, x, y, z = rotvec_to_quaternion(pose[3:6])
    return {
        "timestamp": stamp(t_wall_ns),
        "parent_frame_id": BASE_FRAME,
        "child_frame_id": TCP_FRAME,
        "translation": _vec(pose[:3]),
        "rotation": {"x": float(x), "y": float(y), "z": float(z), "w": float(w)},
    }


def finger_transforms(position: int, t_wall_ns: int) -> list[dict[str, Any]]:
    """Each finger in the TCP frame, along the tool's y axis: open at 0, closed at 255."""
    half = FINGER_STROKE_M * (1.0 - min(max(int(position), 0), 255) / 255.0)
    return [
        {
            "timestamp": stamp(t_wall_ns),
            "parent_frame_id": TCP_FRAME,
            "child_frame_id": name,
            "translation": {"x": 0.0, "y": side * half, "z": 0.0},
            "rotation": dict(_IDENTITY),
        }
        for name, side in zip(FINGER_FRAMES, (1.0, -1.0), strict=True)
    ]


def _entity(entity_id: str, t_wall_ns: int, **primitives: list[dict[str, Any]]) -> dict[str, Any]:
    entity: dict[str, Any] = {
        "timestamp": stamp(t_wall_ns),
        "frame_id": PALM_FRAME,
        "id": entity_id,
        "lifetime": {"sec": 0, "nsec": 0},  # until replaced
        "frame_locked": True,
        "metadata": [],
    }
    for kind in ("arrows", "cubes", "spheres", "cylinders", "lines", "triangles", "texts"):
        entity[kind] = primitives.get(kind, [])
    entity["models"] = []
    return entity


#: stimulus cell (row r = linkage r, column c) -> its square on the palm drawing, m
_CELL_M = 0.018


def palm_stimulus(stimulus: Any, t_wall_ns: int) -> dict[str, Any]:
    """The palm as a scene: the 3x3 stimulus and the three contact points it asks for.

    Each cell is a square whose height and redness are its force; each row's
    contact point (a blue ball) sits over the row's strongest cell, pressed
    in by its force, or lifted off the palm when the row has none (the
    LinkGlide renderer's rule, docs/architecture.md).
    """
    s = np.nan_to_num(np.asarray(stimulus, dtype=np.float64).reshape(3, 3), nan=0.0)
    cubes = []
    for r in range(3):
        for c in range(3):
            level = min(max(float(s[r, c]) / SATURATION_N, 0.0), 1.0)
            height = 0.001 + 0.01 * level
            cubes.append(
                {
                    "pose": {
                        "position": {
                            "x": (c - 1) * _CELL_M,
                            "y": (1 - r) * _CELL_M,
                            "z": height / 2,
                        },
                        "orientation": dict(_IDENTITY),
                    },
                    "size": {"x": 0.9 * _CELL_M, "y": 0.9 * _CELL_M, "z": height},
                    "color": {"r": 0.3 + 0.7 * level, "g": 0.3, "b": 0.3, "a": 0.8},
                }
            )
    spheres = []
    for r in range(3):  # row r drives linkage r: its contact point on the palm
        row = [float(v) for v in s[r]]
        force = max(row)
        c = row.index(force)
        pressed = force > 0  # a row with no force lifts its contact off the palm
        depth = min(max(force / SATURATION_N, 0.0), 1.0) if pressed else 0.0
        spheres.append(
            {
                "pose": {
                    "position": {
                        "x": (c - 1) * _CELL_M if pressed else 1.6 * _CELL_M,
                        "y": (1 - r) * _CELL_M,
                        "z": 0.014 - 0.008 * depth if pressed else 0.03,
                    },
                    "orientation": dict(_IDENTITY),
                },
                "size": {"x": 0.008, "y": 0.008, "z": 0.008},
                "color": {"r": 0.2, "g": 0.6, "b": 1.0, "a": 1.0 if pressed else 0.4},
            }
        )
    return {
        "deletions": [],
        "entities": [
            _entity("stimulus", t_wall_ns, cubes=cubes),
            _entity("contacts", t_wall_ns, spheres=spheres),
        ],
    }


def views(channel: str, record: dict[str, Any], t_wall_ns: int) -> list[tuple[str, dict]]:
    """(topic, message) of every Foxglove message derived from one record; [] for none."""
    if channel == "robot/frame" and record.get("frame") is not None:
        images = pad_images(record["frame"], t_wall_ns)
        return [(f"robot/pads/{f}", m) for f, m in zip(FINGER_FRAMES, images, strict=True)]
    if channel == "robot/arm" and record.get("tcp_pose") is not None:
        return [("robot/tf/tcp", tcp_transform(record["tcp_pose"], t_wall_ns))]
    if channel == "robot/gripper" and record.get("position") is not None:
        fingers = finger_transforms(record["position"], t_wall_ns)
        return [(f"robot/tf/{f}", m) for f, m in zip(FINGER_FRAMES, fingers, strict=True)]
    if channel in ("robot/stimulus", "operator/stimulus"):
        stim = (record.get("decoded") or {}).get("stimulus")
        if stim is not None:
            return [(channel.replace("/stimulus", "/palm"), palm_stimulus(stim, t_wall_ns))]
    return []


# --------------------------------------------------------------------- logs
def log_level(levelno: int) -> int:
    """Python's level -> foxglove.Log's (DEBUG 1, INFO 2, WARNING 3, ERROR 4, FATAL 5)."""
    if levelno >= logging.CRITICAL:
        return 5
    if levelno >= logging.ERROR:
        return 4
    if levelno >= logging.WARNING:
        return 3
    if levelno >= logging.INFO:
        return 2
    return 1 if levelno > logging.NOTSET else 0


def log_message(rec: logging.LogRecord, message: str) -> dict[str, Any]:
    """A log line as a ``foxglove.Log`` (stamped with the line's own wall-clock time)."""
    return {
        "timestamp": stamp(math.floor(rec.created * 1e9)),
        "level": log_level(rec.levelno),
        "message": message,
        "name": rec.name,
        "file": rec.pathname or "",
        "line": max(0, int(rec.lineno or 0)),
    }


# --------------------------------------------------------------------- live
#: the live view's port by default: not the dashboard's 8765 nor the study page's 8766, so
#: one laptop can tunnel to all three
VIEW_PORT = 8767


@dataclasses.dataclass
class FoxgloveLiveConfig:
    enabled: bool = param(False, "serve the recordings live to Foxglove (the 'foxglove' extra)")
    follow: Path | None = param(None, "the session folder being recorded (its *.mcap files)")
    host: str = param("127.0.0.1", "address of Foxglove's WebSocket server")
    port: int = param(VIEW_PORT, "port of Foxglove's WebSocket server (0: any free one)")
    delay_s: float = param(
        1.5, "send each message this long after its recorded time (> the recorders' 1 s flush)"
    )
    poll_interval_s: float = param(0.05, "how often the files are checked for new data")
    allow_remote: bool = param(
        False, "serve on a non-loopback host (anyone reaching it sees the camera and the session)"
    )

    def __post_init__(self) -> None:
        from common.keys.curve import is_loopback_endpoint

        host = f"[{self.host}]" if ":" in self.host else self.host  # an IPv6 address
        if not self.allow_remote and not is_loopback_endpoint(f"tcp://{host}:{self.port}"):
            raise ConfigError(
                f"foxglove.host {self.host!r} is not a loopback address: the live view has no "
                "authentication, so anyone who reaches it sees the camera and the session. Use "
                "an SSH tunnel, or set foxglove.allow_remote=true (deepxpalm view: "
                "--allow-remote) on a network you trust"
            )
        if not self.delay_s > 0:
            raise ConfigError(f"foxglove.delay_s must be positive, not {self.delay_s!r}")
        if not self.poll_interval_s > 0:
            raise ConfigError("foxglove.poll_interval_s must be positive")
