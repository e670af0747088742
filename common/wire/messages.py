"""Every message on the wire between the nodes (docs/protocol.md is the spec).

A ZeroMQ message is one frame: a 4-byte ASCII topic, then a msgpack map.
All maps carry ``v`` (protocol major version), ``type``, ``seq`` (per sender
and type) and ``t_send_ns`` (the sender's monotonic clock). Timestamps are
monotonic nanoseconds of the sender's machine; the receiver maps them to its
own clock with the offset estimated from heartbeats.
"""

from __future__ import annotations

import secrets
from dataclasses import dataclass, field
from typing import Literal, get_args

import numpy as np

PROTOCOL_VERSION = 2
#: what a receiver still reads: version 1 (the same fields under their full names, and a
#: ``type``), from recordings and from nodes of an older build
READABLE_VERSIONS = (1, 2)

RenderMode = Literal["direct", "mask", "mask_ground_truth"]
LinkState = Literal["ok", "stale", "down"]
CommandAction = Literal[
    "gripper_open",
    "gripper_close",
    "gripper_hold",
    "gripper_ease",
    "arm_jog",
    "arm_jog_end",
    "arm_stop",
    "arm_resume",
    "arm_assist",
    "lease_request",
    "lease_grant",
    "lease_release",
]

VideoSignalKind = Literal["offer", "answer", "bye", "closed"]

# the Literals above, as tuples to check against and to list in errors
RENDER_MODES: tuple[str, ...] = get_args(RenderMode)
LINK_STATES: tuple[str, ...] = get_args(LinkState)
COMMAND_ACTIONS: tuple[str, ...] = get_args(CommandAction)
VIDEO_SIGNAL_KINDS: tuple[str, ...] = get_args(VideoSignalKind)
#: the longest session description a video signal may carry (a browser's offer is 3-7 kB)
MAX_SDP_CHARS = 12_000
#: actions that ask for, hand over or give up control of a robot (the control lease)
LEASE_ACTIONS: frozenset[str] = frozenset({"lease_request", "lease_grant", "lease_release"})
#: what an operator key may be (roster, docs/security.md): only controllers may hold the lease
ROLES: tuple[str, ...] = ("controller", "observer", "recorder")
#: roles whose ``arm_stop`` the robot obeys whoever holds the lease: a stop is any person's to
#: press (a shop floor's emergency stop); a recorder is a machine and presses nothing
STOP_ROLES: frozenset[str] = frozenset({"controller", "observer"})


@dataclass(slots=True)
class Stimulus:
    """Robot -> operator: the 3x3 stimulus to render, with what produced it."""

    seq: int
    t_send_ns: int
    t_capture_ns: int  # when the frame it was rendered from was complete
    frame_seq: int
    mode: str  # one of RENDER_MODES
    contact: bool
    stimulus: np.ndarray  # (3, 3) float32 newtons, >= 0, at most one non-zero per row
    pattern: int | None = None  # 0..11; None in direct mode or without contact
    confidence: float | None = None  # 0..1, probability of the recognised pattern
    grip_level: int | None = None  # 1..31 when a gripper reports it
    keyframe: bool = False  # resent unchanged so a lost change cannot persist
    sim_truth_pattern: int | None = None  # simulation only: the pattern actually shown

    session: int | None = None  # random per robot node run (boot id): the replay window's key
    signer: bytes | None = None  # robot: its Ed25519 public key (a signed stream)

    TOPIC = b"STIM"
    TYPE = "stimulus"


@dataclass(slots=True)
class TactileFrame:
    """Robot -> operator, for display only (heatmaps), at a reduced rate."""

    seq: int
    t_send_ns: int
    t_capture_ns: int
    frame_seq: int
    frame: np.ndarray  # FRAME_SHAPE float32 newtons, common view

    session: int | None = None  # random per robot node run (boot id)
    signer: bytes | None = None  # robot: its Ed25519 public key (a signed stream)

    TOPIC = b"FRAM"
    TYPE = "frame"


#: Names of the arm's safety modes, as a robot heartbeat's ``arm_safety_mode`` carries them
#: (the UR controller's numbering): the robot's errors and the dashboard both name them.
ARM_SAFETY_MODES = {
    1: "normal",
    2: "reduced",
    3: "protective stop",
    4: "recovery",
    5: "safeguard stop",
    6: "system emergency stop",
    7: "robot emergency stop",
    8: "violation",
    9: "fault",
}


#: The assist's phases, as a robot heartbeat's ``assist_phase`` numbers them (the index):
#: the robot's assist (robot_side/node/assist.py) and the dashboard both name them.
ASSIST_PHASES = (
    "off",  # not held
    "waiting",  # held, no recognised pattern with contact yet
    "release",  # the gripper opens
    "shift",  # the pad centre moves onto the pipette's axis
    "turn",  # the wrist turns about the closing axis toward 90 deg
    "close",  # the gripper closes at the grip level it held
    "aligned",  # 90 deg centre recognised: stopped, the operator decides to lift
    "gave_up",  # not aligned after the re-grasps allowed: stopped
    "ended",  # a stop, the deadman, a lease change or the operator's own command
)


#: a heartbeat's stats are floats, exact to 2^53: a session is named by its low 32 bits
#: (the robot's ``gripper_command_session``)
SESSION_LOW_MASK = 0xFFFFFFFF


def new_run() -> int:
    """A node run's random ``session`` (its boot id): 63 bits, never 0."""
    return secrets.randbits(63) or 1


@dataclass(slots=True)
class Heartbeat:
    """Both ways: liveness, clock-offset samples, link state and counters."""

    seq: int
    t_send_ns: int
    node: str  # "robot" or "operator"
    state: str  # one of LINK_STATES, as the sender sees the link
    echo_t_send_ns: int | None = None  # t_send_ns of the peer's latest heartbeat
    echo_t_recv_ns: int | None = None  # when that heartbeat arrived (sender's clock)
    stimulus_seq: int | None = None  # robot: the stimulus that is still current
    t_capture_ns: int | None = None  # robot: newest frame that confirmed it
    stats: dict[str, float] = field(default_factory=dict)
    session: int | None = None  # random per node run (boot id), robot and operator
    signer: bytes | None = None  # the sender's Ed25519 public key (signed messages)
    #: operator: the robot run (its ``session``) it last heard: proves the message is of this run
    echo_session: int | None = None
    echo_signer: bytes | None = None  # robot: whose heartbeat the echo fields answer
    lease_holder: bytes | None = None  # robot: the key holding the lease (wire name; an older
    #: build's ``controller`` is read as this)
    lease_pending: bytes | None = None  # robot: a key asking for the lease

    TOPIC = b"HBRT"
    TYPE = "heartbeat"


@dataclass(slots=True)
class Command:
    """Operator -> robot: gripper and arm commands."""

    seq: int
    t_send_ns: int
    action: str  # one of COMMAND_ACTIONS
    grip_level: int | None = None  # gripper_close: 1..31
    velocity: tuple[float, ...] | None = None  # arm_jog: vx vy vz (m/s) wx wy wz (rad/s)
    session: int | None = None  # random per operator run: seq increases within it
    grantee: bytes | None = None  # lease_grant: the key the lease goes to
    signer: bytes | None = None  # the sender's Ed25519 public key (signed messages)
    echo_session: int | None = None  # the robot run the operator last heard (its ``session``)
    #: not on the wire: an ``arm_stop``'s fields that failed their check, ``"field: error"``
    #: (the codec keeps a stop whatever else is wrong with it, and names each bad field here)
    defects: tuple[str, ...] = ()

    TOPIC = b"CMND"
    TYPE = "command"


@dataclass(slots=True)
class VideoSignal:
    """Both ways: a viewer's WebRTC offer and the robot's answer, carried by the link.

    Signalling takes the nodes' own sockets (and the router), so video needs no
    port of its own on either site; the media then flows peer to peer.
    ``viewer`` is a random number per viewing session: it pairs an answer
    with its offer among everyone who reads the robot's stream.
    """

    seq: int
    t_send_ns: int
    kind: str  # one of VIDEO_SIGNAL_KINDS
    viewer: int
    sdp: str | None = None  # offer, answer
    reason: str | None = None  # closed: why the robot ended (or refused) the session
    source: str | None = None  # answer: the camera's name
    width: int | None = None  # answer
    height: int | None = None  # answer
    fps: float | None = None  # answer
    session: int | None = None  # random per node run (boot id), robot and operator
    signer: bytes | None = None  # the sender's Ed25519 public key (signed messages)
    echo_session: int | None = None  # operator: the robot run it last heard

    TOPIC = b"VSIG"
    TYPE = "video_signal"


Message = Stimulus | TactileFrame | Heartbeat | Command | VideoSignal
MESSAGE_TYPES: tuple[type, ...] = (Stimulus, TactileFrame, Heartbeat, Command, VideoSignal)
