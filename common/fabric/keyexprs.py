"""The key expressions of the fabric: where each message travels between sites.

Every message crosses the Zenoh fabric as the same bytes it has on a direct
ZeroMQ link (topic, robot name, msgpack map, signature: docs/protocol.md); the
key expression only routes it, so the router's access control can tell who
may put and read what without reading a payload.

    dxp/ROBOT/stimulus                  robot -> operators   best-effort, latest value
    dxp/ROBOT/frame                     robot -> operators   best-effort, latest value
    dxp/ROBOT/heartbeat                 robot -> operators   best-effort, latest value
    dxp/ROBOT/video                     robot -> operators   reliable (answers to offers)
    dxp/ROBOT/op/OPERATOR/command       operator -> robot    reliable
    dxp/ROBOT/op/OPERATOR/stop          operator -> robot    reliable, and best-effort copies
    dxp/ROBOT/op/OPERATOR/heartbeat     operator -> robot    best-effort, latest value
    dxp/ROBOT/op/OPERATOR/video         operator -> robot    reliable (offers, byes)

ROBOT is a robot name (the roster's ``name`` or one of its ``names``),
OPERATOR the operator's roster name, which is also its certificate's common
name: the router lets an operator put only under its own name, and a robot
only under its own names (router_side/acl.py).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from common.errors import ConfigError
from common.wire.codec import DecodeError, check_robot_name
from common.wire.messages import Command, Heartbeat, Message, Stimulus, TactileFrame, VideoSignal

ROOT = "dxp"
#: what the robot sends, by message type
ROBOT_KINDS: dict[type, str] = {
    Stimulus: "stimulus",
    TactileFrame: "frame",
    Heartbeat: "heartbeat",
    VideoSignal: "video",
}
#: what an operator sends, by message type (an ``arm_stop`` goes under "stop")
OPERATOR_KINDS: dict[type, str] = {Command: "command", Heartbeat: "heartbeat", VideoSignal: "video"}
STOP = "stop"
#: a stop's best-effort copy, under a key of its own: the router's rate gate keeps one time
#: per sender and key, so on the stop's own key whichever of the two reached it first passed
#: and the other was dropped, the reliable stop too when its copy's datagram overtook it
STOP_COPY = "stop_copy"
#: the kinds that carry an ``arm_stop``
STOP_KINDS = frozenset({STOP, STOP_COPY})
#: best-effort, dropped under congestion, never retransmitted: only the newest counts. A
#: heartbeat is one too: the next one (50 ms later) says all it said, and held back behind a
#: lost packet it would make a fresh stimulus look stale and a live operator look silent
LATEST_VALUE_KINDS = frozenset({"stimulus", "frame", "heartbeat"})

#: an operator name must be one chunk of a key expression: no '/', no wildcard
_CHUNK = re.compile(r"[A-Za-z0-9_.-]{1,64}")


def check_operator_name(name: str) -> str:
    """``name`` if it can stand in a key expression; ConfigError with the rule otherwise."""
    if not _CHUNK.fullmatch(name) or name in {".", ".."}:
        raise ConfigError(
            f"operator name {name!r} cannot cross the fabric: use 1-64 of A-Z a-z 0-9 _ . -"
        )
    return name


def _robot(name: str | bytes) -> str:
    try:
        return check_robot_name(name).decode("ascii")
    except DecodeError as e:
        raise ConfigError(str(e)) from None


def robot_key(robot: str | bytes, kind: str) -> str:
    """Where a robot puts one kind of message (``ROBOT_KINDS``)."""
    return f"{ROOT}/{_robot(robot)}/{kind}"


def operator_key(robot: str | bytes, operator: str, kind: str) -> str:
    """Where an operator puts one kind of message to one robot (``OPERATOR_KINDS`` or stop)."""
    return f"{ROOT}/{_robot(robot)}/op/{check_operator_name(operator)}/{kind}"


def robot_inbox(robot: str | bytes) -> str:
    """What a robot subscribes to: every operator's messages to it."""
    return f"{ROOT}/{_robot(robot)}/op/*/*"


def robot_inbox_for(robot: str | bytes, kind: str) -> str:
    """What a robot subscribes to for one kind: every operator's messages of that kind."""
    return f"{ROOT}/{_robot(robot)}/op/*/{kind}"


def kind_of(msg: Message, from_robot: bool) -> str:
    """The key's last chunk for ``msg`` (``stop`` for an operator's ``arm_stop``)."""
    kinds = ROBOT_KINDS if from_robot else OPERATOR_KINDS
    kind = kinds.get(type(msg))
    if kind is None:
        side = "a robot" if from_robot else "an operator"
        raise ValueError(f"{type(msg).__name__} is not something {side} sends")
    if kind == "command" and msg.action == "arm_stop":
        return STOP
    return kind


@dataclass(frozen=True)
class Wanted:
    """What an operator node reads of one robot (its subscriptions)."""

    frames: bool = True
    video: bool = False

    def keys(self, robot: str | bytes) -> tuple[str, ...]:
        kinds = ["stimulus", "heartbeat"]
        if self.frames:
            kinds.append("frame")
        if self.video:
            kinds.append("video")
        return tuple(robot_key(robot, k) for k in kinds)
