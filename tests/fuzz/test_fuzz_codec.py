"""The codec under property-based fuzzing: only DecodeError escapes, and what decodes is in spec.

No sockets here (tests/fuzz/test_fuzz_*node*.py push the same mutants at
running nodes); this is where many examples per second are cheap.
"""

from __future__ import annotations

import math

import msgpack
import pytest
from fuzz_mutate import Mutator, spec_violations, valid_message
from hypothesis import given, settings
from hypothesis import strategies as st

from common.wire.codec import MAX_MESSAGE_BYTES, DecodeError, decode, encode
from common.wire.codec_schema import WIRE_KEYS
from common.wire.messages import MESSAGE_TYPES

TOPICS = [b"STIM", b"FRAM", b"HBRT", b"CMND"]
TYPES = ["stimulus", "frame", "heartbeat", "command"]
FIELDS = [
    "v",
    "type",
    "seq",
    "t_send_ns",
    "t_capture_ns",
    "frame_seq",
    "mode",
    "contact",
    "stimulus",
    "pattern",
    "confidence",
    "grip_level",
    "keyframe",
    "sim_truth_pattern",
    "frame",
    "node",
    "state",
    "echo_t_send_ns",
    "echo_t_recv_ns",
    "stimulus_seq",
    "stats",
    "action",
    "velocity",
]

scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**63), max_value=2**64 - 1),
    st.floats(),
    st.floats(width=32),
    st.text(max_size=16),
    st.binary(max_size=40),
    st.sampled_from(["stimulus", "direct", "mask", "robot", "ok", "arm_jog", "gripper_close"]),
    st.binary(min_size=36, max_size=36),
)
values = st.recursive(
    scalars,
    lambda inner: st.one_of(
        st.lists(inner, max_size=5), st.dictionaries(st.text(max_size=4), inner, max_size=4)
    ),
    max_leaves=6,
)


def _check(data: bytes) -> None:
    try:
        msg = decode(data)
    except DecodeError:
        return
    assert spec_violations(msg) == [], (data, msg)
    # and what decodes encodes again to something that decodes the same
    again = decode(encode(msg))
    assert type(again) is type(msg)


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=300))
def test_random_bytes(data):
    _check(data)


@pytest.mark.slow
@pytest.mark.untimed  # no timing checked
@settings(max_examples=200, deadline=None)
@given(st.sampled_from(TOPICS), st.binary(max_size=300))
def test_random_bytes_behind_a_real_topic(topic, data):
    _check(topic + data)


@st.composite
def maps(draw) -> bytes:
    topic_i = draw(st.integers(0, 3))
    type_i = draw(st.sampled_from([topic_i, topic_i, topic_i, (topic_i + 1) % 4]))
    body = {"v": draw(st.sampled_from([1, 2, 2, 0, 3])), "type": TYPES[type_i]}
    for name in draw(st.lists(st.sampled_from(FIELDS), max_size=12, unique=True)):
        body[name] = draw(values)
    if body["v"] != 1:  # version 2's keys (a spelled-out name now and then: unknown there)
        spell = draw(st.integers(0, 9)) == 0
        body = {k if spell else WIRE_KEYS.get(k, k): v for k, v in body.items()}
    single = draw(st.booleans())
    try:
        return TOPICS[topic_i] + msgpack.packb(body, use_bin_type=True, use_single_float=single)
    except (OverflowError, ValueError):
        return TOPICS[topic_i] + b"\x80"


@pytest.mark.slow
@pytest.mark.untimed  # no timing checked
@settings(max_examples=200, deadline=None)
@given(maps())
def test_maps_of_protocol_fields_with_any_values(data):
    _check(data)


@pytest.mark.slow
@pytest.mark.untimed  # no timing checked
@settings(max_examples=100, deadline=None)
@given(st.randoms(use_true_random=False))
def test_valid_messages_round_trip(rnd):
    msg = valid_message(rnd)
    data = encode(msg)
    assert len(data) <= MAX_MESSAGE_BYTES
    back = decode(data)
    assert type(back) is type(msg) and spec_violations(back) == []


@pytest.mark.slow
@pytest.mark.untimed  # no timing checked
def test_ten_thousand_structure_aware_mutants():
    mut = Mutator(seed=31)
    decoded = 0
    for _ in range(10_000):
        data = mut.mutant()
        _check(data)
        try:
            decode(data)
            decoded += 1
        except DecodeError:
            pass
    assert 0 < decoded < 10_000 * 0.3  # most mutants are rejected, some still decode


@pytest.mark.parametrize("cls", MESSAGE_TYPES, ids=lambda c: c.TYPE)
def test_every_type_survives_every_truncation(cls):
    import random

    data = encode(valid_message(random.Random(1), cls))
    for cut in range(len(data)):
        with pytest.raises(DecodeError):
            decode(data[:cut])


def test_nesting_deeper_than_msgpack_allows_is_a_decode_error():
    deep = b"\x91" * 100_000 + b"\x01"  # 100,000 nested one-element arrays
    with pytest.raises(DecodeError):
        decode(b"HBRT" + deep)


def test_non_finite_floats_anywhere_are_rejected():
    import random

    rnd = random.Random(4)
    for cls in MESSAGE_TYPES:
        body = msgpack.unpackb(encode(valid_message(rnd, cls))[4:])
        for key, value in body.items():  # version 2's keys: "v" is the version
            if isinstance(value, float) or (isinstance(value, int) and key != "v"):
                for bad in (math.nan, math.inf, -math.inf):
                    b = dict(body, **{key: bad})
                    with pytest.raises(DecodeError):
                        decode(cls.TOPIC + msgpack.packb(b, use_bin_type=True))
