"""The live view's Foxglove WebSocket server, and a robot's telemetry as its channels.

``LiveServer`` is the one server behind every live view: ``deepxpalm view``
and ``deepxpalm record``'s ``foxglove`` table (``common/live_view/session_files.py``
feeds it a session's recordings). It runs Foxglove's own server (the
``foxglove-sdk`` package, the ``foxglove`` extra) in a context of its own,
offers its clients no capability (no publishing, services or parameters: a
client can only watch), and keeps one channel per topic, whoever feeds it.

``WireView`` turns what a robot sends on its link (stimuli, raw frames,
heartbeats, as ``common.wire.codec`` decodes them) into the topics and messages a
recording holds (docs/recording.md, "Foxglove"): ``robot/pads/finger_1`` and
``finger_2`` from the raw frames, ``robot/palm`` and ``robot/stimulus`` from
the stimuli, ``robot/link`` (the heartbeat's state and counters) and
``robot/tf/tcp`` (the arm's pose among them) from the heartbeats. So the
layout that opens a recording (docs/foxglove-layout.json) shows the link live.

The server has no authentication and no check of a browser's ``Origin``:
foxglove-sdk offers neither (docs/security.md, "The live view"). So it binds
loopback unless ``allow_remote`` says otherwise (``FoxgloveLiveConfig``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import math
from collections import Counter
from typing import Any

import numpy as np

from common.clocks.clock import wall_offset_ns
from common.errors import ConfigError
from common.recording import foxglove
from common.recording.foxglove import FoxgloveLiveConfig
from common.wire.messages import Heartbeat, Message, Stimulus, TactileFrame

log = logging.getLogger(__name__)

#: a robot heartbeat's stats keys of the arm's TCP pose, m and rotation vector in rad (the
#: robot's ``TELEMETRY_POSE_KEYS``, robot_side/arm/base.py; a test holds the two alike)
POSE_KEYS = ("arm_x", "arm_y", "arm_z", "arm_rx", "arm_ry", "arm_rz")
#: the recordings' schema names for their own JSON channels (common/recording/mcap_recorder.py)
SCHEMA_PREFIX = "deepxpalm/"
#: the topics ``WireView`` serves for one robot (a prefix ``NAME/`` before each with several)
WIRE_TOPICS: frozenset[str] = frozenset(
    {
        "robot/stimulus",
        "robot/link",
        "robot/palm",
        "robot/tf/tcp",
        *(f"robot/pads/{f}" for f in foxglove.FINGER_FRAMES),
    }
)


def _import_sdk() -> Any:
    try:
        import foxglove as sdk
    except ImportError:
        raise ConfigError(
            "the live Foxglove view needs the 'foxglove' extra: pip install '.[foxglove]'"
        ) from None
    return sdk


class LiveServer:
    """Foxglove's WebSocket server on ``config.host``:``config.port``, with its channels."""

    def __init__(self, config: FoxgloveLiveConfig) -> None:
        sdk = _import_sdk()
        self._sdk = sdk
        self.host = config.host
        self.context = sdk.Context()  # channels of this server only, not the process's
        self._channels: dict[str, Any] = {}
        try:
            self.server = sdk.start_server(
                name="deepxpalm", host=config.host, port=config.port, context=self.context
            )
        except Exception as e:  # the sdk raises its own error types
            raise ConfigError(
                f"cannot serve Foxglove on {config.host}:{config.port}: {e} (is the port in use? "
                "choose another port)"
            ) from None
        self.port = int(self.server.port)

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"ws://{host}:{self.port}"

    def has(self, topic: str) -> bool:
        return topic in self._channels

    def channel(
        self,
        topic: str,
        *,
        schema_name: str = "",
        schema_encoding: str = "",
        schema_data: bytes = b"",
        message_encoding: str = "json",
    ) -> Any:
        """The channel of ``topic``: made on first use, the same one after (a restarted
        node's file, or a second source of the topic, goes on the same channel)."""
        known = self._channels.get(topic)
        if known is not None:
            return known
        schema = (
            self._sdk.Schema(name=schema_name, encoding=schema_encoding, data=schema_data)
            if schema_name
            else None
        )
        channel = self._sdk.Channel(
            topic, schema=schema, message_encoding=message_encoding, context=self.context
        )
        self._channels[topic] = channel
        return channel

    def typed_channel(self, topic: str, type_name: str) -> Any:
        """A channel of one of Foxglove's types (``common.recording.foxglove.SCHEMAS``)."""
        return self.channel(
            topic,
            schema_name=type_name,
            schema_encoding="jsonschema",
            schema_data=json.dumps(foxglove.SCHEMAS[type_name]).encode(),
        )

    def json_channel(self, topic: str, description: str = "") -> Any:
        """A channel of plain JSON maps, named as a recording names its own."""
        schema: dict[str, Any] = {"title": topic, "type": "object"}
        if description:
            schema["description"] = description
        return self.channel(
            topic,
            schema_name=SCHEMA_PREFIX + topic,
            schema_encoding="jsonschema",
            schema_data=json.dumps(schema).encode(),
        )

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.server.stop()


def jsonable(value: Any) -> Any:
    """A JSON-ready copy: arrays as lists, bytes as hex, non-finite numbers as null."""
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, (bytes, bytearray)):
        return bytes(value).hex()
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (np.floating, float)):
        v = float(value)
        return v if math.isfinite(v) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


def _dump(message: dict[str, Any]) -> bytes:
    return json.dumps(message, separators=(",", ":"), allow_nan=False).encode()


class WireView:
    """A robot's decoded telemetry, logged on ``server``'s channels as a recording has it.

    ``prefix_robots``: each topic under the robot's name (``cell1/robot/palm``),
    for a view of several robots; one robot's view has the recordings' topics.
    """

    def __init__(self, server: LiveServer, *, prefix_robots: bool = False) -> None:
        self.server = server
        self.prefix_robots = prefix_robots
        self.counters: Counter[str] = Counter()
        self._wall_offset_ns = wall_offset_ns()

    def _topic(self, robot: bytes, topic: str) -> str:
        if self.prefix_robots and robot:
            return f"{robot.decode('ascii')}/{topic}"
        return topic

    def _log_view(self, robot: bytes, topic: str, message: dict[str, Any], t_wall: int) -> None:
        channel = self.server.typed_channel(self._topic(robot, topic), foxglove.VIEW_TOPICS[topic])
        channel.log(_dump(message), log_time=t_wall)
        self.counters["sent"] += 1

    def _log_json(self, robot: bytes, topic: str, message: dict[str, Any], t_wall: int) -> None:
        channel = self.server.json_channel(self._topic(robot, topic))
        channel.log(_dump(jsonable(message)), log_time=t_wall)
        self.counters["sent"] += 1

    def take(self, robot: bytes, msg: Message, t_recv_ns: int) -> None:
        """One message as received (``t_recv_ns``: this PC's monotonic clock)."""
        t_wall = t_recv_ns + self._wall_offset_ns
        if isinstance(msg, Stimulus):
            fields = {f.name: getattr(msg, f.name) for f in dataclasses.fields(msg)}
            self._log_json(robot, "robot/stimulus", {"seq": msg.seq, "decoded": fields}, t_wall)
            self._log_view(
                robot, "robot/palm", foxglove.palm_stimulus(msg.stimulus, t_wall), t_wall
            )
        elif isinstance(msg, TactileFrame):
            for finger, image in zip(
                foxglove.FINGER_FRAMES, foxglove.pad_images(msg.frame, t_wall), strict=True
            ):
                self._log_view(robot, f"robot/pads/{finger}", image, t_wall)
        elif isinstance(msg, Heartbeat):
            self._log_json(robot, "robot/link", {"state": msg.state, **msg.stats}, t_wall)
            if all(k in msg.stats for k in POSE_KEYS):
                pose = [msg.stats[k] for k in POSE_KEYS]
                self._log_view(robot, "robot/tf/tcp", foxglove.tcp_transform(pose, t_wall), t_wall)
        else:
            self.counters["not_shown"] += 1
