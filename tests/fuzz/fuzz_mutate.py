"""Structure-aware mutation of wire messages, and an independent check of what decodes.

Random bytes almost never get past msgpack; mutating valid messages does:
it reaches every field check of the codec (types, ranges, sizes, NaN and
infinity, nesting) with messages that are one mistake away from valid.
``Mutator`` makes such messages from a seeded corpus; ``spec_violations``
re-states docs/protocol.md on its own, so a message that decodes is held
to the spec and not to the codec's idea of it.
"""

from __future__ import annotations

import math
import random
import struct
from collections.abc import Callable
from typing import Any

import msgpack
import numpy as np

from common.wire.codec import MAX_MESSAGE_BYTES, DecodeError, decode, encode, field_names
from common.wire.codec_schema import BY_TOPIC, WIRE_KEYS
from common.wire.messages import (
    COMMAND_ACTIONS,
    LINK_STATES,
    RENDER_MODES,
    Command,
    Heartbeat,
    Message,
    Stimulus,
    TactileFrame,
)

TOPICS = (b"STIM", b"FRAM", b"HBRT", b"CMND")
U63 = 2**63 - 1

# ----------------------------------------------------------------- corpus


def _stimulus_array(rng: random.Random) -> np.ndarray:
    out = np.zeros((3, 3), np.float32)
    for row in range(3):
        if rng.random() < 0.7:
            out[row, rng.randrange(3)] = rng.choice([rng.uniform(0.01, 9.0), 9.0, 0.05])
    return out


def valid_message(rng: random.Random, kind: type | None = None) -> Message:
    """A random message that follows the spec, optional fields sometimes set."""
    kind = kind or rng.choice((Stimulus, TactileFrame, Heartbeat, Command))
    seq, t = rng.randrange(1, 10**6), rng.randrange(10**9, 10**15)

    def maybe(value: Any) -> Any:
        return value if rng.random() < 0.5 else None

    if kind is Stimulus:
        contact = rng.random() < 0.8
        return Stimulus(
            seq=seq,
            t_send_ns=t,
            t_capture_ns=t - rng.randrange(10**6),
            frame_seq=rng.randrange(10**6),
            mode=rng.choice(RENDER_MODES),
            contact=contact,
            stimulus=_stimulus_array(rng) if contact else np.zeros((3, 3), np.float32),
            pattern=maybe(rng.randrange(12)),
            confidence=maybe(rng.random()),
            grip_level=maybe(rng.randint(1, 31)),
            keyframe=rng.random() < 0.2,
            sim_truth_pattern=maybe(rng.randrange(12)),
        )
    if kind is TactileFrame:
        frame = np.zeros((2, 10, 10), np.float32)
        frame[:, 3:7, 2:8] = rng.uniform(0, 9)
        return TactileFrame(
            seq=seq, t_send_ns=t, t_capture_ns=t - 1000, frame_seq=rng.randrange(10**6), frame=frame
        )
    if kind is Heartbeat:
        return Heartbeat(
            seq=seq,
            t_send_ns=t,
            node=rng.choice(("robot", "operator")),
            state=rng.choice(LINK_STATES),
            echo_t_send_ns=maybe(t - 5000),
            echo_t_recv_ns=maybe(t - 4000),
            stimulus_seq=maybe(rng.randrange(10**6)),
            t_capture_ns=maybe(t - 10**6),
            stats={f"c{i}": float(rng.randrange(1000)) for i in range(rng.randrange(0, 20))},
        )
    action = rng.choice(COMMAND_ACTIONS)
    return Command(
        seq=seq,
        t_send_ns=t,
        action=action,
        grip_level=rng.randint(1, 31) if action == "gripper_close" else None,
        velocity=tuple(rng.uniform(-0.05, 0.05) for _ in range(6)) if action == "arm_jog" else None,
    )


# ------------------------------------------------------------- the pools

_F32_SPECIAL = [math.nan, math.inf, -math.inf, -1.0, 9.0001, 1e30, -0.0, 5e-45]


def _bad_f32_bytes(rng: random.Random, n: int) -> bytes:
    vals = [rng.uniform(0, 9) for _ in range(n)]
    for _ in range(rng.randint(1, 3)):
        vals[rng.randrange(n)] = rng.choice(_F32_SPECIAL)
    return struct.pack(f"<{n}f", *vals)


def _deep(depth: int, leaf: Any) -> Any:
    out = leaf
    for _ in range(depth):
        out = [out]
    return out


def junk_value(rng: random.Random) -> Any:
    """A value of some type, often the wrong one: the type-confusion pool."""
    choices: list[Callable[[], Any]] = [
        lambda: None,
        lambda: True,
        lambda: False,
        lambda: 0,
        lambda: -1,
        lambda: rng.choice([U63, U63 + 1, 2**64 - 1, -(2**63)]),
        lambda: rng.choice([math.nan, math.inf, -math.inf, 1e308, -1e308, 5e-324, -0.0, 0.5]),
        lambda: "",
        lambda: "x" * rng.choice([1, 40, 3000]),
        lambda: b"",
        lambda: rng.randbytes(rng.choice([1, 35, 36, 37, 72, 800])),
        lambda: [],
        lambda: [rng.uniform(-1, 1) for _ in range(rng.choice([5, 6, 7]))],
        lambda: [math.nan] * 6,
        lambda: ["a"] * 6,
        lambda: {},
        lambda: {"a": math.nan},
        lambda: {"k": {"n": [1, 2, {"x": None}]}},
        lambda: _deep(rng.choice([3, 50, 400]), 1),
        lambda: msgpack.ExtType(rng.randrange(128), b"\x01\x02"),
        lambda: msgpack.Timestamp(1, 2),
    ]
    return rng.choice(choices)()


def _edge_number(rng: random.Random) -> Any:
    return rng.choice(
        [
            -1,
            0,
            1,
            12,
            31,
            32,
            U63,
            U63 + 1,
            2**64 - 1,
            -(2**63),
            math.nan,
            math.inf,
            -math.inf,
            1e308,
            -1e-300,
            1.0000001,
            -0.0,
            True,
        ]
    )


# ---------------------------------------------------------------- mutator


class Mutator:
    """Seeded mutations of valid encoded messages, from one flipped bit to nested junk."""

    def __init__(self, seed: int, kinds: tuple[type, ...] | None = None, pool: int = 256) -> None:
        self.rng = random.Random(seed)
        self.kinds = kinds
        # Valid messages are made once: mutating is the work, not building the originals.
        # Their maps are kept by field name (the mutations name fields) and framed again in
        # either version the receivers read (``_framed``)
        self.pool: list[tuple[bytes, dict]] = []
        for _ in range(pool):
            data = encode(valid_message(self.rng, self.rng.choice(kinds) if kinds else None))
            self.pool.append((data, field_names(msgpack.unpackb(data[4:], raw=False))))
        self.byte_ops = [
            self._flip_bits,
            self._set_bytes,
            self._truncate,
            self._extend,
            self._splice,
            self._swap_topic,
        ]
        self.body_ops = [
            self._drop_field,
            self._confuse_field,
            self._edge_field,
            self._bad_array,
            self._bad_version,
            self._bad_type,
            self._non_map_body,
            self._bad_keys,
            self._bloat,
            self._velocity,
            self._stats,
        ]

    def valid(self) -> bytes:
        return self.rng.choice(self.pool)[0]

    def mutant(self) -> bytes:
        """One message with one to three mutations, most of them structural."""
        data, body = self.rng.choice(self.pool)
        body = dict(body)
        for n in range(self.rng.choice((1, 1, 1, 2, 3))):
            if self.rng.random() < 0.75:
                data = self._body_op(data, body if n == 0 else None)
            else:
                data = self.rng.choice(self.byte_ops)(data)
        return data

    # -- byte level ------------------------------------------------------
    def _flip_bits(self, data: bytes) -> bytes:
        if not data:
            return b"\xff"
        b = bytearray(data)
        for _ in range(self.rng.randint(1, 8)):
            i = self.rng.randrange(len(b))
            b[i] ^= 1 << self.rng.randrange(8)
        return bytes(b)

    def _set_bytes(self, data: bytes) -> bytes:
        if not data:
            return b"\xc1"
        b = bytearray(data)
        for _ in range(self.rng.randint(1, 4)):
            b[self.rng.randrange(len(b))] = self.rng.choice(
                [0x00, 0xFF, 0x7F, 0x80, 0xC0, 0xC1, 0xC4, 0xCA, 0xCB, 0xDC, 0xDE, 0xDF]
            )
        return bytes(b)

    def _truncate(self, data: bytes) -> bytes:
        return data[: self.rng.randrange(len(data))] if data else data

    def _extend(self, data: bytes) -> bytes:
        n = self.rng.choice([1, 2, 16, 500])
        return data + self.rng.randbytes(n)

    def _splice(self, data: bytes) -> bytes:
        i, j = sorted(self.rng.randrange(len(data) + 1) for _ in range(2))
        op = self.rng.randrange(3)
        if op == 0:
            return data[:i] + data[j:]  # delete
        if op == 1:
            return data[:j] + data[i:j] + data[j:]  # duplicate
        return data[:i] + self.rng.randbytes(8) + data[i:]

    def _swap_topic(self, data: bytes) -> bytes:
        topic = self.rng.choice([*TOPICS, b"stim", b"XXXX", b"\x00\x00\x00\x00", b"STI"])
        return topic + data[4:]

    # -- structure level -------------------------------------------------
    def _body_op(self, data: bytes, body: dict | None = None) -> bytes:
        if body is None:
            try:
                body = msgpack.unpackb(data[4:], raw=False, strict_map_key=False)
            except Exception:
                return self._flip_bits(data)  # an earlier byte mutation broke it; keep breaking
        if not isinstance(body, dict):
            return self._flip_bits(data)
        out = self.rng.choice(self.body_ops)(body)
        if isinstance(out, dict):
            out = self._framed(data[:4], out)
        if isinstance(out, bytes):
            return data[:4] + out
        single = self.rng.random() < 0.2  # float 32 on the wire must be accepted too
        try:
            packed = msgpack.packb(out, use_bin_type=True, use_single_float=single)
        except (ValueError, OverflowError, TypeError):
            packed = msgpack.packb(str(out)[:200], use_bin_type=True)
        return data[:4] + packed

    def _framed(self, topic: bytes, body: dict) -> dict:
        """A map by field name as version 2 keys it (most) or as version 1 spelled it."""
        cls = BY_TOPIC.get(topic)
        if self.rng.random() < 0.25 and cls is not None:
            return {"v": 1, "type": cls.TYPE, **body} if body.get("v") == 2 else body
        return {WIRE_KEYS.get(k, k) if isinstance(k, str) else k: v for k, v in body.items()}

    def _key(self, body: dict) -> Any:
        return self.rng.choice(list(body)) if body else "v"

    def _drop_field(self, body: dict) -> dict:
        body.pop(self._key(body), None)
        return body

    def _confuse_field(self, body: dict) -> dict:
        body[self._key(body)] = junk_value(self.rng)
        return body

    def _edge_field(self, body: dict) -> dict:
        numeric = [k for k, v in body.items() if isinstance(v, (int, float))]
        key = self.rng.choice(numeric) if numeric else self._key(body)
        body[key] = _edge_number(self.rng)
        return body

    def _bad_array(self, body: dict) -> dict:
        key = "frame" if "frame" in body else "stimulus"
        n = 200 if key == "frame" else 9
        choice = self.rng.randrange(6)
        if choice == 0:
            body[key] = _bad_f32_bytes(self.rng, n)
        elif choice == 1:
            body[key] = bytes(4 * n + self.rng.choice([-4, -1, 1, 4, 4 * n]))
        elif choice == 2:
            body[key] = struct.pack(f"<{n}d", *([1.0] * n))  # float 64: twice the bytes
        elif choice == 3:
            vals = [0.0] * n
            vals[0] = vals[1] = 2.0  # two non-zero cells in a row (stimulus)
            body[key] = struct.pack(f"<{n}f", *vals)
        elif choice == 4:
            body[key] = [1.0] * n  # a list, not bin
        else:
            body[key] = "A" * (4 * n)  # a str of the right length
        return body

    def _bad_version(self, body: dict) -> dict:
        body["v"] = self.rng.choice([0, 2, -1, "1", None, 2**64 - 1, [1], 255])
        return body

    def _bad_type(self, body: dict) -> dict:
        body["type"] = self.rng.choice(
            ["stimulus", "frame", "heartbeat", "command", "", "STIM", None, 1, ["stimulus"]]
        )
        return body

    def _non_map_body(self, body: dict) -> bytes:
        value = self.rng.choice(
            [list(body.items())[:3], 1, "stimulus", None, b"\x00" * 4, _deep(200, body.get("v"))]
        )
        try:
            return msgpack.packb(value, use_bin_type=True)
        except (ValueError, TypeError):
            return b"\xc1"

    def _bad_keys(self, body: dict) -> bytes:
        """Keys that are not strings: bin keys (same bytes) or integer keys."""
        if self.rng.random() < 0.5:
            items = {k.encode() if isinstance(k, str) else k: v for k, v in body.items()}
        else:
            items = dict(body)
            items[self.rng.randrange(-5, 5)] = 1
        try:
            return msgpack.packb(items, use_bin_type=True)
        except (ValueError, TypeError):
            return b"\xc1"

    def _bloat(self, body: dict) -> dict:
        """Unknown keys, up to the size limit: ignored if nothing else is wrong."""
        budget = self.rng.choice([100, 4000, MAX_MESSAGE_BYTES - 400])
        body[f"x{self.rng.randrange(100)}"] = "z" * budget
        if self.rng.random() < 0.5:
            body[self._key(body)] = junk_value(self.rng)
        return body

    def _velocity(self, body: dict) -> dict:
        body["action"] = self.rng.choice([*COMMAND_ACTIONS, "arm_move", "", None])
        body["velocity"] = self.rng.choice(
            [
                [1e308] * 6,
                [math.nan, 0, 0, 0, 0, 0],
                [0, 0, math.inf, 0, 0, 0],
                [0.1] * 5,
                [0.1] * 7,
                ["0.1"] * 6,
                [True] * 6,
                [[0.1]] * 6,
                None,
                {"vx": 1},
                [-(2**63)] * 6,
            ]
        )
        body["grip_level"] = _edge_number(self.rng)
        return body

    def _stats(self, body: dict) -> dict:
        choice = self.rng.randrange(5)
        if choice == 0:
            body["stats"] = {f"k{i}": 1.0 for i in range(65)}
        elif choice == 1:
            body["stats"] = {"a": math.nan}
        elif choice == 2:
            body["stats"] = {"a": {"b": 1}}
        elif choice == 3:
            body["stats"] = [1, 2, 3]
        else:
            body["stats"] = {"a": "1"}
        return body


# --------------------------------------------------------------- oracle


def classify(data: bytes) -> Message | None:
    """The decoded message, or None when the codec rejects it (the only allowed failure)."""
    try:
        return decode(data)
    except DecodeError:
        return None


def spec_violations(msg: Message) -> list[str]:
    """What in a decoded message breaks docs/protocol.md, checked independently of the codec."""
    bad: list[str] = []

    def uint(name: str, v: Any, required: bool = True) -> None:
        if v is None and not required:
            return
        if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= U63:
            bad.append(f"{name}={v!r} is not a uint")

    def finite(name: str, v: Any) -> float:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            bad.append(f"{name}={v!r} is not a finite number")
            return 0.0
        return float(v)

    uint("seq", msg.seq)
    uint("t_send_ns", msg.t_send_ns)
    if isinstance(msg, Stimulus):
        uint("t_capture_ns", msg.t_capture_ns)
        uint("frame_seq", msg.frame_seq)
        if msg.mode not in RENDER_MODES:
            bad.append(f"mode {msg.mode!r}")
        if not isinstance(msg.contact, bool):
            bad.append("contact not bool")
        s = np.asarray(msg.stimulus)
        if s.shape != (3, 3) or s.dtype != np.float32:
            bad.append(f"stimulus shape {s.shape} {s.dtype}")
        elif not np.isfinite(s).all() or s.min() < 0 or s.max() > 9:
            bad.append(f"stimulus values {s.tolist()}")
        elif ((s > 0).sum(axis=1) > 1).any():
            bad.append("two non-zero cells in a row")
        for name, lo, hi in (
            ("pattern", 0, 11),
            ("grip_level", 1, 31),
            ("sim_truth_pattern", 0, 11),
        ):
            v = getattr(msg, name)
            if v is not None and (
                isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi
            ):
                bad.append(f"{name}={v!r}")
        if msg.confidence is not None and not 0 <= finite("confidence", msg.confidence) <= 1:
            bad.append(f"confidence={msg.confidence}")
    elif isinstance(msg, TactileFrame):
        uint("t_capture_ns", msg.t_capture_ns)
        f = np.asarray(msg.frame)
        if f.shape != (2, 10, 10) or not np.isfinite(f).all() or f.min() < 0 or f.max() > 9:
            bad.append("frame out of spec")
    elif isinstance(msg, Heartbeat):
        if msg.node not in ("robot", "operator") or msg.state not in LINK_STATES:
            bad.append(f"node/state {msg.node!r}/{msg.state!r}")
        for name in ("echo_t_send_ns", "echo_t_recv_ns", "stimulus_seq", "t_capture_ns"):
            uint(name, getattr(msg, name), required=False)
        if not isinstance(msg.stats, dict) or len(msg.stats) > 64:
            bad.append("stats not a map of at most 64")
        else:
            for k, v in msg.stats.items():
                if not isinstance(k, str):
                    bad.append(f"stats key {k!r}")
                finite(f"stats.{k}", v)
    elif isinstance(msg, Command):
        if msg.action not in COMMAND_ACTIONS:
            bad.append(f"action {msg.action!r}")
        if msg.grip_level is not None and (
            isinstance(msg.grip_level, bool) or not 1 <= msg.grip_level <= 31
        ):
            bad.append(f"grip_level={msg.grip_level!r}")
        if msg.velocity is not None:
            if len(msg.velocity) != 6:
                bad.append("velocity length")
            for i, v in enumerate(msg.velocity):
                finite(f"velocity[{i}]", v)
    else:
        bad.append(f"unknown message class {type(msg).__name__}")
    return bad


# ------------------------------------------------------- producer process
def produce(conn: Any, seed: int, kinds: list[str] | None, total: int, batch: int) -> None:
    """Child process: mutants with the codec's verdict, in batches, until ``total``."""
    from common.wire.messages import MESSAGE_TYPES

    by_name = {cls.TYPE: cls for cls in MESSAGE_TYPES}
    mut = Mutator(seed, tuple(by_name[k] for k in kinds) if kinds else None)
    made = 0
    while made < total:
        items = []
        for _ in range(min(batch, total - made)):
            data = mut.mutant()
            if len(data) > MAX_MESSAGE_BYTES:
                # ZeroMQ drops these before the codec (MAXMSGSIZE) and closes the connection
                items.append(("oversize", str(len(data)), data))
                continue
            try:
                msg = decode(data)
            except DecodeError as e:
                items.append(("rejected", type(e).__name__, data))
            except Exception as e:
                items.append(("escaped", f"{type(e).__name__}: {e}", data))
            else:
                problems = spec_violations(msg)
                verdict = "spec" if problems else "valid"
                items.append((verdict, type(msg).TYPE + " " + "; ".join(problems), data))
        made += len(items)
        conn.send_bytes(msgpack.packb(items, use_bin_type=True))
    conn.send_bytes(b"")
    conn.close()
