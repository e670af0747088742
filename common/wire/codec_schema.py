"""What each message may hold: the field checks, the schemas, and the errors a check raises.

A message that decodes is safe to act on: right version and type, every
required field present with the right type, every number finite and in
range, arrays of the right shape. Each field's check raises a
``DecodeError`` subclass that names the problem (``common.wire.codec`` decodes
with them).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from typing import Any

import numpy as np

from common.errors import DeepXPalmError
from common.tactile.contract import (
    FRAME_SHAPE,
    N_GRIP_LEVELS,
    N_PATTERNS,
    SATURATION_N,
    STIMULUS_SHAPE,
)
from common.wire.messages import (
    COMMAND_ACTIONS,
    LINK_STATES,
    MAX_SDP_CHARS,
    MESSAGE_TYPES,
    RENDER_MODES,
    VIDEO_SIGNAL_KINDS,
    Command,
    Heartbeat,
    Stimulus,
    TactileFrame,
    VideoSignal,
)

MAX_STATS = 64
_U63 = 2**63 - 1


class DecodeError(DeepXPalmError, ValueError):
    """A message was rejected; it must be counted and dropped, never acted on."""


class MalformedMessageError(DecodeError):
    """Not a topic followed by a msgpack map."""


class MultipartMessageError(MalformedMessageError):
    """More than one ZeroMQ frame: every message on this protocol is a single frame."""


class MessageTooLargeError(DecodeError):
    """Longer than ``MAX_MESSAGE_BYTES``."""


class UnsupportedVersionError(DecodeError):
    """The protocol major version is not this build's."""


class UnknownMessageTypeError(DecodeError):
    """The topic or ``type`` names no known message."""


class MissingFieldError(DecodeError):
    """A required field is absent."""


class FieldTypeError(DecodeError):
    """A field has the wrong type or shape."""


class NonFiniteValueError(DecodeError):
    """A number is NaN or infinite."""


class OutOfRangeError(DecodeError):
    """A number is outside the range its field allows."""


class RobotNameError(DecodeError):
    """A robot name that is empty, too long or holds a byte outside ``NAME_CHARS``."""


class WrongRobotError(DecodeError):
    """A message named for another robot than the one this socket serves."""


class SignatureError(DecodeError):
    """A ``sig`` that is misplaced, lacks its ``signer``, or does not verify."""


# ---------------------------------------------------------------- field checks
Check = Callable[[str, Any], Any]


def _uint(name: str, v: Any) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise FieldTypeError(f"{name} must be an unsigned integer, not {type(v).__name__}")
    if not 0 <= v <= _U63:
        raise OutOfRangeError(f"{name} = {v} is outside 0..2**63-1")
    return v


def _int_range(lo: int, hi: int) -> Check:
    def check(name: str, v: Any) -> int:
        if isinstance(v, bool) or not isinstance(v, int):
            raise FieldTypeError(f"{name} must be an integer, not {type(v).__name__}")
        if not lo <= v <= hi:
            raise OutOfRangeError(f"{name} = {v} is outside {lo}..{hi}")
        return v

    return check


def _finite(name: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise FieldTypeError(f"{name} must be a number, not {type(v).__name__}")
    v = float(v)
    if not math.isfinite(v):
        raise NonFiniteValueError(f"{name} is {v}")
    return v


def _float_range(lo: float, hi: float) -> Check:
    def check(name: str, v: Any) -> float:
        v = _finite(name, v)
        if not lo <= v <= hi:
            raise OutOfRangeError(f"{name} = {v} is outside {lo}..{hi}")
        return v

    return check


def _bool(name: str, v: Any) -> bool:
    if not isinstance(v, bool):
        raise FieldTypeError(f"{name} must be true or false, not {type(v).__name__}")
    return v


def _enum(values: tuple[str, ...]) -> Check:
    def check(name: str, v: Any) -> str:
        if not isinstance(v, str):
            raise FieldTypeError(f"{name} must be a string, not {type(v).__name__}")
        if v not in values:
            raise OutOfRangeError(f"{name} = {v!r} is not one of {list(values)}")
        return v

    return check


def _f32_array(shape: tuple[int, ...], lo: float, hi: float) -> Check:
    nbytes = 4 * math.prod(shape)

    def check(name: str, v: Any) -> np.ndarray:
        if not isinstance(v, bytes) or len(v) != nbytes:
            raise FieldTypeError(f"{name} must be {nbytes} bytes of little-endian float32")
        arr = np.frombuffer(v, dtype="<f4").reshape(shape)
        if not np.isfinite(arr).all():
            raise NonFiniteValueError(f"{name} holds a non-finite value")
        if arr.min() < lo or arr.max() > hi:
            raise OutOfRangeError(f"{name} holds values outside {lo}..{hi}")
        return arr.astype(np.float32)  # native, writable copy

    return check


_STIMULUS = struct.Struct("<9f")


def _stimulus_array(name: str, v: Any) -> np.ndarray:
    """The 3x3 stimulus, checked in plain Python: nine numbers are too few for NumPy to pay."""
    if not isinstance(v, bytes) or len(v) != _STIMULUS.size:
        raise FieldTypeError(f"{name} must be {_STIMULUS.size} bytes of little-endian float32")
    cells = _STIMULUS.unpack(v)
    for value in cells:
        if not math.isfinite(value):
            raise NonFiniteValueError(f"{name} holds a non-finite value")
        if not 0.0 <= value <= SATURATION_N:
            raise OutOfRangeError(f"{name} holds values outside 0.0..{SATURATION_N}")
    for r in (0, 3, 6):
        if (cells[r] > 0) + (cells[r + 1] > 0) + (cells[r + 2] > 0) > 1:
            raise OutOfRangeError(f"{name} has more than one non-zero cell in a row")
    return np.array(cells, dtype=np.float32).reshape(STIMULUS_SHAPE)


def _velocity(name: str, v: Any) -> tuple[float, ...]:
    if not isinstance(v, (list, tuple)) or len(v) != 6:
        raise FieldTypeError(f"{name} must be a list of 6 numbers")
    return tuple(_finite(f"{name}[{i}]", x) for i, x in enumerate(v))


def _stats(name: str, v: Any) -> dict[str, float]:
    if not isinstance(v, dict) or len(v) > MAX_STATS:
        raise FieldTypeError(f"{name} must be a map of at most {MAX_STATS} numbers")
    out = {}
    for k, x in v.items():
        if not isinstance(k, str):
            raise FieldTypeError(f"{name} keys must be strings")
        out[k] = _finite(f"{name}.{k}", x)
    return out


def _text(max_chars: int) -> Check:
    def check(name: str, v: Any) -> str:
        if not isinstance(v, str):
            raise FieldTypeError(f"{name} must be a string, not {type(v).__name__}")
        if len(v) > max_chars:
            raise OutOfRangeError(f"{name} is {len(v)} characters, more than {max_chars}")
        return v

    return check


def _bin(size: int) -> Check:
    def check(name: str, v: Any) -> bytes:
        if not isinstance(v, bytes) or len(v) != size:
            raise FieldTypeError(f"{name} must be {size} bytes")
        return v

    return check


_KEY = _bin(32)  # an Ed25519 public key
_SESSION = _int_range(1, _U63)  # random per sender run: the replay window's key

# (field, check, required). Optional fields may be absent or nil.
_COMMON = [("seq", _uint, True), ("t_send_ns", _uint, True)]
SCHEMAS: dict[type, list[tuple[str, Check, bool]]] = {
    Stimulus: [
        *_COMMON,
        ("t_capture_ns", _uint, True),
        ("frame_seq", _uint, True),
        ("mode", _enum(RENDER_MODES), True),
        ("contact", _bool, True),
        ("stimulus", _stimulus_array, True),
        ("pattern", _int_range(0, N_PATTERNS - 1), False),
        ("confidence", _float_range(0.0, 1.0), False),
        ("grip_level", _int_range(1, N_GRIP_LEVELS), False),
        ("keyframe", _bool, False),
        ("sim_truth_pattern", _int_range(0, N_PATTERNS - 1), False),
        ("session", _SESSION, False),
        ("signer", _KEY, False),
    ],
    TactileFrame: [
        *_COMMON,
        ("t_capture_ns", _uint, True),
        ("frame_seq", _uint, True),
        ("frame", _f32_array(FRAME_SHAPE, 0.0, SATURATION_N), True),
        ("session", _SESSION, False),
        ("signer", _KEY, False),
    ],
    Heartbeat: [
        *_COMMON,
        ("node", _enum(("robot", "operator")), True),
        ("state", _enum(LINK_STATES), True),
        ("echo_t_send_ns", _uint, False),
        ("echo_t_recv_ns", _uint, False),
        ("stimulus_seq", _uint, False),
        ("t_capture_ns", _uint, False),
        ("stats", _stats, False),
        ("session", _SESSION, False),
        ("signer", _KEY, False),
        ("echo_signer", _KEY, False),
        ("lease_holder", _KEY, False),
        ("lease_pending", _KEY, False),
        ("echo_session", _SESSION, False),
    ],
    Command: [
        *_COMMON,
        ("action", _enum(COMMAND_ACTIONS), True),
        ("grip_level", _int_range(1, N_GRIP_LEVELS), False),
        ("velocity", _velocity, False),
        ("session", _SESSION, False),
        ("grantee", _KEY, False),
        ("signer", _KEY, False),
        ("echo_session", _SESSION, False),
    ],
    VideoSignal: [
        *_COMMON,
        ("kind", _enum(VIDEO_SIGNAL_KINDS), True),
        ("viewer", _int_range(1, _U63), True),
        ("sdp", _text(MAX_SDP_CHARS), False),
        ("reason", _text(200), False),
        ("source", _text(64), False),
        ("width", _int_range(1, 8192), False),
        ("height", _int_range(1, 8192), False),
        ("fps", _float_range(0.0, 1000.0), False),
        ("session", _SESSION, False),
        ("signer", _KEY, False),
        ("echo_session", _SESSION, False),
    ],
}
BY_TOPIC = {cls.TOPIC: cls for cls in MESSAGE_TYPES}
#: version 2's map keys: one character per field name, the same for every message type
#: (docs/protocol.md, Keys on the wire). Version 1 spelled the names out and carried a
#: ``type`` the topic already says: a third of a stimulus's bytes, where the path across
#: sites has room for about two 1,200-byte datagrams a round trip after a loss
WIRE_KEYS: dict[str, str] = {
    "v": "v", "sig": "sig",
    "seq": "s", "t_send_ns": "t", "session": "r", "signer": "i", "echo_session": "R",
    "t_capture_ns": "c", "frame_seq": "f", "mode": "m", "contact": "k", "stimulus": "x",
    "pattern": "p", "confidence": "q", "grip_level": "g", "keyframe": "K",
    "sim_truth_pattern": "P", "frame": "F",
    "node": "n", "state": "l", "echo_t_send_ns": "e", "echo_t_recv_ns": "E",
    "stimulus_seq": "S", "stats": "z", "echo_signer": "I", "lease_holder": "h",
    "lease_pending": "H",
    "action": "a", "velocity": "u", "grantee": "G",
    "kind": "d", "viewer": "w", "sdp": "o", "reason": "y", "source": "C", "width": "W",
    "height": "V", "fps": "Z",
}  # fmt: skip
#: the field name of each version-2 key
FIELD_NAMES: dict[str, str] = {key: name for name, key in WIRE_KEYS.items()}
#: per type, every key its map may hold that the schema checks
KNOWN_KEYS = {
    cls: frozenset(("v", "type", "sig", *(name for name, _, _ in fields)))
    for cls, fields in SCHEMAS.items()
}
#: per type, {name an older build sent: the field's name now}; read as the new name when the
#: new one is absent (the signature covers the bytes as sent, so a renamed field still verifies)
RENAMED_FIELDS: dict[type, dict[str, str]] = {Heartbeat: {"controller": "lease_holder"}}
#: how deep an unknown value may nest before the message is refused as malformed
MAX_UNKNOWN_DEPTH = 8
#: per type, (field, its label in error messages, check, required): labels made once, not per field
DECODE_PLAN = {
    cls: [(name, f"{cls.TYPE}.{name}", check, required) for name, check, required in fields]
    for cls, fields in SCHEMAS.items()
}
