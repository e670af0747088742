"""msgpack codec for ``common.messages``: validates everything on decode.

A message that decodes is safe to act on: right version and type, every
required field present with the right type, every number finite and in
range, arrays of the right shape. Anything else raises a ``DecodeError``
subclass that names the problem; the caller counts it and drops the message.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from typing import Any

import msgpack
import numpy as np

from common.errors import DeepXPalmError
from common.messages import (
    COMMAND_ACTIONS,
    LINK_STATES,
    MAX_SDP_CHARS,
    MESSAGE_TYPES,
    PROTOCOL_VERSION,
    RENDER_MODES,
    VIDEO_SIGNAL_KINDS,
    Command,
    Heartbeat,
    Message,
    Stimulus,
    TactileFrame,
    VideoSignal,
)
from common.tactile import FRAME_SHAPE, N_GRIP_LEVELS, N_PATTERNS, SATURATION_N, STIMULUS_SHAPE

TOPIC_LEN = 4
MAX_MESSAGE_BYTES = 16 * 1024
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
_BY_TOPIC = {cls.TOPIC: cls for cls in MESSAGE_TYPES}
#: per type, every key its map may hold that the schema checks
_KNOWN_KEYS = {
    cls: frozenset(("v", "type", "sig", *(name for name, _, _ in fields)))
    for cls, fields in SCHEMAS.items()
}
#: per type, {name an older build sent: the field's name now}; read as the new name when the
#: new one is absent (the signature covers the bytes as sent, so a renamed field still verifies)
RENAMED_FIELDS: dict[type, dict[str, str]] = {Heartbeat: {"controller": "lease_holder"}}
#: how deep an unknown value may nest before the message is refused as malformed
MAX_UNKNOWN_DEPTH = 8
#: per type, (field, its label in error messages, check, required): labels made once, not per field
_DECODE_PLAN = {
    cls: [(name, f"{cls.TYPE}.{name}", check, required) for name, check, required in fields]
    for cls, fields in SCHEMAS.items()
}


# --------------------------------------------------------------------- encode
_PLAIN = (int, float, str, bool)
_F32 = np.dtype("<f4")


def _wire_value(v: Any) -> Any:
    if type(v) in _PLAIN:  # most fields: as they are, no isinstance chain
        return v
    if isinstance(v, np.ndarray):
        if v.dtype == _F32 and v.flags.c_contiguous:
            return v.tobytes()
        return np.ascontiguousarray(v, dtype=_F32).tobytes()
    if isinstance(v, tuple):
        return list(v)
    if isinstance(v, (np.integer, np.floating, np.bool_)):
        return v.item()
    return v


def encode(msg: Message, name: bytes = b"", signer: Any = None) -> bytes:
    """Topic (+ robot name) + msgpack map. Optional fields that are None are left out.

    ``signer`` (a ``common.signing.Signer``): the message carries its public
    key as ``signer`` and, as the map's last entry, ``sig``: the signature
    over every byte before that entry (docs/protocol.md, Signed messages).
    """
    cls = type(msg)
    body: dict[str, Any] = {"v": PROTOCOL_VERSION, "type": cls.TYPE}
    for field_name, _, required in SCHEMAS[cls]:
        value = getattr(msg, field_name)
        if value is None and not required:
            continue
        body[field_name] = _wire_value(value)
    if cls is Heartbeat and not msg.stats:
        body.pop("stats", None)
    prefix = name_prefix(cls.TOPIC, name) if name else cls.TOPIC
    if signer is None:
        return prefix + msgpack.packb(body, use_bin_type=True)
    body["signer"] = signer.public
    body["sig"] = _NO_SIG  # a placeholder of the right size: the map header counts it
    signed = (prefix + msgpack.packb(body, use_bin_type=True))[:-SIG_ENTRY_BYTES]
    return signed + SIG_TAG + signer.sign(signed)


# ---------------------------------------------------------------- robot names
#: a robot's name on the wire: 1 to 32 of these bytes, after the topic and a length byte
NAME_CHARS = frozenset(b"abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_-.")
MAX_NAME_LEN = 32


def check_robot_name(name: str | bytes) -> bytes:
    """The name as wire bytes; raises ``RobotNameError`` for a name the protocol forbids."""
    raw = name.encode("ascii", "replace") if isinstance(name, str) else bytes(name)
    if not 1 <= len(raw) <= MAX_NAME_LEN or not NAME_CHARS.issuperset(raw):
        raise RobotNameError(
            f"robot name {name!r} must be 1 to {MAX_NAME_LEN} of A-Z a-z 0-9 _ - ."
        )
    return raw


def name_prefix(topic: bytes, name: bytes = b"") -> bytes:
    """What a frame starts with: the topic, then (named robots) the name's length and the name.

    It is also the ZeroMQ subscription that selects one message type of one
    robot: the length byte makes ``cell1`` and ``cell10`` different prefixes.
    """
    if not name:
        return topic
    return topic + bytes((len(name),)) + name


def split_name(data: bytes) -> tuple[bytes, int]:
    """(robot name or b"", where the msgpack body starts) of a frame.

    After the topic a msgpack map starts with 0x80-0x8f, 0xde or 0xdf; a
    name's length byte is 1 to 32, so the two can never be confused.
    """
    n = data[TOPIC_LEN] if len(data) > TOPIC_LEN else 0
    if not 1 <= n <= MAX_NAME_LEN:
        return b"", TOPIC_LEN
    end = TOPIC_LEN + 1 + n
    name = bytes(data[TOPIC_LEN + 1 : end])
    if len(name) != n or not NAME_CHARS.issuperset(name):
        raise RobotNameError(f"malformed robot name after topic {bytes(data[:TOPIC_LEN])!r}")
    return name, end


# ----------------------------------------------------------------- signatures
#: the ``sig`` entry as it ends a signed frame: fixstr "sig", bin 8 of 64 bytes, the signature
SIG_TAG = b"\xa3sig\xc4\x40"
SIG_ENTRY_BYTES = len(SIG_TAG) + 64
_NO_SIG = bytes(64)


# --------------------------------------------------------------------- decode
def decode(data: bytes) -> Message:
    """Validate and build a message; raises a ``DecodeError`` subclass."""
    return decode_named(data)[1]


def decode_named(data: bytes) -> tuple[bytes, Message]:
    """(robot name or b"", message) of a frame that may carry a robot's name.

    A message with a ``sig`` is returned only if the signature verifies, so
    a decoded message's ``signer`` is the key that really signed it.
    """
    if len(data) > MAX_MESSAGE_BYTES:
        raise MessageTooLargeError(f"{len(data)} bytes exceeds {MAX_MESSAGE_BYTES}")
    if len(data) <= TOPIC_LEN:
        raise MalformedMessageError(f"{len(data)} bytes is too short for a message")
    topic = bytes(data[:TOPIC_LEN])
    cls = _BY_TOPIC.get(topic)
    if cls is None:
        raise UnknownMessageTypeError(f"unknown topic {topic!r}")
    name, start = split_name(data)
    try:
        body = msgpack.unpackb(data[start:], raw=False, strict_map_key=True)
    except Exception as e:  # msgpack raises several unrelated types
        raise MalformedMessageError(f"{topic.decode()} payload is not msgpack: {e}") from None
    if not isinstance(body, dict):
        raise MalformedMessageError(f"{topic.decode()} payload is not a map")
    version = body.get("v")
    if type(version) is not int or version != PROTOCOL_VERSION:  # not True, not 1.0
        raise UnsupportedVersionError(
            f"protocol version {version!r}; this build speaks {PROTOCOL_VERSION}"
        )
    if body.get("type") != cls.TYPE:
        raise UnknownMessageTypeError(
            f"type {body.get('type')!r} does not match topic {topic!r} ({cls.TYPE!r})"
        )
    if cls in RENAMED_FIELDS:
        _rename_old_fields(body, RENAMED_FIELDS[cls])
    if cls is Command and body.get("action") == "arm_stop":
        kwargs = _lenient_stop(body)
    else:
        if not _KNOWN_KEYS[cls].issuperset(body):  # one C-level test on the common path
            _check_unknown_keys(cls, body)
        kwargs = {}
        for field_name, label, check, required in _DECODE_PLAN[cls]:
            value = body.get(field_name)
            if value is None:
                if required:
                    raise MissingFieldError(f"{cls.TYPE} is missing required field {field_name!r}")
                continue
            kwargs[field_name] = check(label, value)
    if "sig" in body:
        _check_signature(cls, data, body)
    elif "signer" in kwargs:
        raise SignatureError(f"{cls.TYPE} names a signer but carries no sig")
    return name, cls(**kwargs)


def _rename_old_fields(body: dict[str, Any], renamed: dict[str, str]) -> None:
    for old, new in renamed.items():
        if old in body:
            value = body.pop(old)
            body.setdefault(new, value)


#: an arm_stop's fields it cannot do without: the signature's (checked as for any message)
_STOP_NEEDS = frozenset({"signer"})
#: what a required field of a stop becomes when it is unreadable (the defect names it)
_STOP_FALLBACK = {"seq": 0, "t_send_ns": 0}


def _lenient_stop(body: dict[str, Any]) -> dict[str, Any]:
    """An ``arm_stop``'s fields: a bad one is named in ``defects``, never a reason to drop it.

    A stop that arrives must stop the arm, whatever else is wrong with it (a
    malformed send time, a stray field): refusing it could only keep the arm
    moving. Its version, type, action and signature are checked as for any
    message (a forged stop is still refused); every other field that fails
    its check is left out, or set to 0 if required, and ``"field: error"``
    goes in ``defects`` for the robot to log and count (robot_side/node/commands/command_gate.py
    decides how far such a stop is believed).
    """
    defects: list[str] = []
    if not _KNOWN_KEYS[Command].issuperset(body):
        try:
            _check_unknown_keys(Command, body)
        except DecodeError as e:
            defects.append(f"(other): {e}")
    kwargs: dict[str, Any] = {}
    for field_name, label, check, required in _DECODE_PLAN[Command]:
        value = body.get(field_name)
        if value is None:
            if required:
                kwargs[field_name] = _STOP_FALLBACK[field_name]
                defects.append(f"{field_name}: missing")
            continue
        try:
            kwargs[field_name] = check(label, value)
        except DecodeError as e:
            if field_name in _STOP_NEEDS:
                raise
            if required:
                kwargs[field_name] = _STOP_FALLBACK[field_name]
            defects.append(f"{field_name}: {e}")
    kwargs["defects"] = tuple(defects)
    return kwargs


def _check_signature(cls: type, data: bytes, body: dict[str, Any]) -> None:
    from common.signing import verify

    sig = body["sig"]
    tail = bytes(data[-SIG_ENTRY_BYTES:])
    if not isinstance(sig, bytes) or len(sig) != 64 or tail != SIG_TAG + sig:
        raise SignatureError(f"{cls.TYPE}.sig must be 64 bytes and the map's last entry")
    signer = body.get("signer")
    if not isinstance(signer, bytes):
        raise SignatureError(f"{cls.TYPE} carries a sig but no signer")
    if not verify(signer, sig, bytes(data[:-SIG_ENTRY_BYTES])):
        raise SignatureError(f"{cls.TYPE} signature does not verify for its signer")


def _check_unknown_keys(cls: type, body: dict[Any, Any]) -> None:
    """Unknown keys are ignored, but only if they hold nothing the protocol forbids anywhere."""
    known = _KNOWN_KEYS[cls]
    for key, value in body.items():
        if type(key) is not str:
            raise FieldTypeError(f"{cls.TYPE} has a map key that is not a string: {key!r:.40}")
        if key not in known:
            _check_unknown_value(f"{cls.TYPE}.{key}", value, 0)


def _check_unknown_value(label: str, value: Any, depth: int) -> None:
    if depth > MAX_UNKNOWN_DEPTH:
        raise MalformedMessageError(f"{label} nests deeper than {MAX_UNKNOWN_DEPTH} levels")
    if type(value) is float:
        if not math.isfinite(value):
            raise NonFiniteValueError(f"{label} is {value}")
    elif isinstance(value, dict):
        for k, v in value.items():
            if type(k) is not str:
                raise FieldTypeError(f"{label} has a map key that is not a string: {k!r:.40}")
            _check_unknown_value(f"{label}.{k}", v, depth + 1)
    elif isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            _check_unknown_value(f"{label}[{i}]", v, depth + 1)


def topic_of(data: bytes) -> bytes:
    return bytes(data[:TOPIC_LEN])
