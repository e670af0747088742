"""msgpack codec for ``common.wire.messages``: validates everything on decode.

A message that decodes is safe to act on: right version and type, every
required field present with the right type, every number finite and in
range, arrays of the right shape. Anything else raises a ``DecodeError``
subclass that names the problem; the caller counts it and drops the message.
The checks and the schemas are ``common.wire.codec_schema``'s; this module is the
wire: encoding, robot names, signatures and decoding.
"""

from __future__ import annotations

import math
from typing import Any

import msgpack
import numpy as np

from common.wire.codec_schema import (
    BY_TOPIC,
    DECODE_PLAN,
    FIELD_NAMES,
    KNOWN_KEYS,
    MAX_STATS,
    MAX_UNKNOWN_DEPTH,
    RENAMED_FIELDS,
    SCHEMAS,
    WIRE_KEYS,
    DecodeError,
    FieldTypeError,
    MalformedMessageError,
    MessageTooLargeError,
    MissingFieldError,
    MultipartMessageError,
    NonFiniteValueError,
    OutOfRangeError,
    RobotNameError,
    SignatureError,
    UnknownMessageTypeError,
    UnsupportedVersionError,
    WrongRobotError,
)
from common.wire.messages import (
    PROTOCOL_VERSION,
    READABLE_VERSIONS,
    Command,
    Heartbeat,
    Message,
)

__all__ = [
    "MAX_MESSAGE_BYTES",
    "MAX_NAME_LEN",
    "MAX_STATS",
    "SCHEMAS",
    "SIG_ENTRY_BYTES",
    "SIG_TAG",
    "TOPIC_LEN",
    "DecodeError",
    "FieldTypeError",
    "MalformedMessageError",
    "MessageTooLargeError",
    "MissingFieldError",
    "MultipartMessageError",
    "NonFiniteValueError",
    "OutOfRangeError",
    "RobotNameError",
    "SignatureError",
    "UnknownMessageTypeError",
    "UnsupportedVersionError",
    "WrongRobotError",
    "check_robot_name",
    "decode",
    "decode_named",
    "encode",
    "field_names",
    "name_prefix",
    "split_name",
    "topic_of",
]

TOPIC_LEN = 4
MAX_MESSAGE_BYTES = 16 * 1024


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


#: per type, (field, its key on the wire, required), in the schema's order
_ENCODE_PLAN = {
    cls: [(name, WIRE_KEYS[name], required) for name, _, required in fields]
    for cls, fields in SCHEMAS.items()
}
_STATS_KEY, _SIGNER_KEY = WIRE_KEYS["stats"], WIRE_KEYS["signer"]


def encode(msg: Message, name: bytes = b"", signer: Any = None) -> bytes:
    """Topic (+ robot name) + msgpack map. Optional fields that are None are left out.

    The map's keys are version 2's: one character per field (``WIRE_KEYS``).

    ``signer`` (a ``common.wire.signing.Signer``): the message carries its public
    key as ``signer`` and, as the map's last entry, ``sig``: the signature
    over every byte before that entry (docs/protocol.md, Signed messages).
    """
    cls = type(msg)
    body: dict[str, Any] = {"v": PROTOCOL_VERSION}
    for field_name, key, required in _ENCODE_PLAN[cls]:
        value = getattr(msg, field_name)
        if value is None and not required:
            continue
        body[key] = _wire_value(value)
    if cls is Heartbeat and not msg.stats:
        body.pop(_STATS_KEY, None)
    prefix = name_prefix(cls.TOPIC, name) if name else cls.TOPIC
    if signer is None:
        return prefix + msgpack.packb(body, use_bin_type=True)
    body[_SIGNER_KEY] = signer.public
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
    cls = BY_TOPIC.get(topic)
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
    if type(version) is not int or version not in READABLE_VERSIONS:  # not True, not 1.0
        raise UnsupportedVersionError(
            f"protocol version {version!r}; this build speaks {PROTOCOL_VERSION}"
            f" and reads {' and '.join(map(str, READABLE_VERSIONS))}"
        )
    if version == PROTOCOL_VERSION:
        body = field_names(body)
    else:
        _check_version_1(cls, topic, body)
    if cls is Command and body.get("action") == "arm_stop":
        kwargs = _lenient_stop(body)
    else:
        if not KNOWN_KEYS[cls].issuperset(body):  # one C-level test on the common path
            _check_unknown_keys(cls, body)
        kwargs = {}
        for field_name, label, check, required in DECODE_PLAN[cls]:
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


def field_names(body: dict[Any, Any]) -> dict[Any, Any]:
    """A version-2 map with its fields' names as keys (``WIRE_KEYS`` read backwards).

    A key that is no field's stays unknown (it is prefixed with ``?``, so a
    name spelled out cannot stand in for its one-character key).
    """
    names = FIELD_NAMES
    return {names.get(k) or (f"?{k}" if type(k) is str else k): v for k, v in body.items()}


def _check_version_1(cls: type, topic: bytes, body: dict[str, Any]) -> None:
    """Version 1's map: its ``type`` must match the topic; old names read as the new."""
    if body.get("type") != cls.TYPE:
        raise UnknownMessageTypeError(
            f"type {body.get('type')!r} does not match topic {topic!r} ({cls.TYPE!r})"
        )
    for old, new in RENAMED_FIELDS.get(cls, {}).items():
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
    if not KNOWN_KEYS[Command].issuperset(body):
        try:
            _check_unknown_keys(Command, body)
        except DecodeError as e:
            defects.append(f"(other): {e}")
    kwargs: dict[str, Any] = {}
    for field_name, label, check, required in DECODE_PLAN[Command]:
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
    from common.wire.signing import verify

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
    known = KNOWN_KEYS[cls]
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
