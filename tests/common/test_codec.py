"""The codec is where untrusted bytes become actions: everything bad must be named and dropped."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from tests_support import on_the_wire, readable, stimulus

from common.wire import codec
from common.wire.codec import (
    SIG_ENTRY_BYTES,
    SIG_TAG,
    DecodeError,
    FieldTypeError,
    MalformedMessageError,
    MessageTooLargeError,
    MissingFieldError,
    NonFiniteValueError,
    OutOfRangeError,
    SignatureError,
    UnknownMessageTypeError,
    UnsupportedVersionError,
    decode,
    encode,
)
from common.wire.messages import Command, Heartbeat, Stimulus, TactileFrame
from common.wire.signing import Signer

body_of, rebuild = readable, on_the_wire


def test_every_message_round_trips():
    msgs = [
        stimulus(),
        stimulus(session=2**63 - 1),  # a robot run's boot id (docs/protocol.md)
        stimulus(
            pattern=None,
            confidence=None,
            grip_level=None,
            contact=False,
            stimulus=np.zeros((3, 3), np.float32),
            mode="direct",
        ),
        TactileFrame(
            seq=1,
            t_send_ns=5,
            t_capture_ns=4,
            frame_seq=9,
            frame=np.linspace(0, 9, 200, dtype=np.float32).reshape(2, 10, 10),
        ),
        Heartbeat(
            seq=2,
            t_send_ns=10,
            node="robot",
            state="ok",
            echo_t_send_ns=3,
            echo_t_recv_ns=4,
            stimulus_seq=7,
            t_capture_ns=9,
            stats={"frames": 12.0},
            session=99,
        ),
        Command(seq=3, t_send_ns=11, action="arm_jog", velocity=(0.01, 0, 0, 0, 0, 0.1)),
        Command(seq=4, t_send_ns=12, action="gripper_close", grip_level=31),
    ]
    for msg in msgs:
        out = decode(encode(msg))
        assert type(out) is type(msg)
        for name in msg.__slots__:
            a, b = getattr(msg, name), getattr(out, name)
            if isinstance(a, np.ndarray):
                np.testing.assert_array_equal(a, b)
            else:
                assert a == b, name


@pytest.mark.parametrize(
    ("mutate", "error"),
    [
        (lambda b: b.update(v=3), UnsupportedVersionError),
        (lambda b: b.pop("v"), UnsupportedVersionError),
        (lambda b: b.update(v=1, type="command"), UnknownMessageTypeError),
        (lambda b: b.update(v=1), UnknownMessageTypeError),  # version 1 says its type
        (lambda b: b.pop("seq"), MissingFieldError),
        (lambda b: b.pop("stimulus"), MissingFieldError),
        (lambda b: b.update(seq="7"), FieldTypeError),
        (lambda b: b.update(seq=-1), OutOfRangeError),
        (lambda b: b.update(contact=1), FieldTypeError),
        (lambda b: b.update(confidence=float("nan")), NonFiniteValueError),
        (lambda b: b.update(confidence=float("inf")), NonFiniteValueError),
        (lambda b: b.update(confidence=1.5), OutOfRangeError),
        (lambda b: b.update(pattern=12), OutOfRangeError),
        (lambda b: b.update(grip_level=0), OutOfRangeError),
        (lambda b: b.update(session=0), OutOfRangeError),
        (lambda b: b.update(session=b"boot"), FieldTypeError),
        (lambda b: b.update(mode="fancy"), OutOfRangeError),
        (lambda b: b.update(stimulus=b"\x00" * 35), FieldTypeError),
        (lambda b: b.update(stimulus=[0.0] * 9), FieldTypeError),
        (lambda b: b.update(stimulus=np.full(9, np.nan, "<f4").tobytes()), NonFiniteValueError),
        (lambda b: b.update(stimulus=np.full(9, -1, "<f4").tobytes()), OutOfRangeError),
        (lambda b: b.update(stimulus=np.full(9, 50, "<f4").tobytes()), OutOfRangeError),
        (
            lambda b: b.update(stimulus=np.array([1, 1, 0] + [0] * 6, "<f4").tobytes()),
            OutOfRangeError,
        ),
    ],
)
def test_bad_stimulus_fields_are_named(mutate, error):
    body = body_of(encode(stimulus()))
    mutate(body)
    with pytest.raises(error):
        decode(rebuild(b"STIM", body))


def test_unknown_fields_are_ignored_for_forward_compatibility():
    body = body_of(encode(stimulus()))
    body["added_in_v1_5"] = {"anything": [1, 2]}
    assert decode(rebuild(b"STIM", body)).seq == 7


def test_version_2_keys_are_one_character_and_a_name_spelled_out_is_not_read_for_one():
    body = msgpack.unpackb(encode(stimulus())[4:], raw=False)
    assert body["v"] == 2 and "type" not in body and all(len(k) == 1 for k in body)
    spelled = body_of(encode(stimulus()))  # the fields by name, under version 2
    with pytest.raises(MissingFieldError):
        decode(b"STIM" + msgpack.packb(spelled, use_bin_type=True))


def test_a_version_1_message_from_an_older_build_or_a_recording_still_decodes():
    signer = Signer.generate()
    msg = stimulus(session=5, signer=signer.public)
    body = dict(body_of(encode(msg)), v=1, type="stimulus")
    body.pop("signer")
    packed = rebuild(b"STIM", dict(body, signer=signer.public, sig=bytes(64)))
    signed = packed[:-SIG_ENTRY_BYTES]
    old = decode(signed + SIG_TAG + signer.sign(signed))  # the signature covers v1's bytes
    assert old.seq == msg.seq and old.signer == signer.public
    assert np.array_equal(old.stimulus, msg.stimulus) and old.pattern == msg.pattern


def test_a_signed_named_stimulus_fits_a_fifth_of_a_datagram():
    """The stream across sites is mostly stimuli: at 60 a second, each byte is 480 bit/s of a
    path that after a loss carries about two 1,200-byte datagrams a round trip."""
    big = {"seq": 2**24, "t_send_ns": 2**60, "t_capture_ns": 2**60, "frame_seq": 2**24}
    msg = stimulus(session=2**62, keyframe=True, **big)  # the stamps of a machine up a while
    data = encode(msg, b"cell1", Signer.generate())
    assert len(data) <= 240, len(data)


@pytest.mark.parametrize(
    ("data", "error"),
    [
        (b"", MalformedMessageError),
        (b"STIM", MalformedMessageError),
        (b"XXXX" + msgpack.packb({}), UnknownMessageTypeError),
        (b"STIM" + b"\xc1\xc1", MalformedMessageError),
        (b"STIM" + msgpack.packb([1, 2, 3]), MalformedMessageError),
        (b"STIM" + b"\x00" * (codec.MAX_MESSAGE_BYTES + 1), MessageTooLargeError),
    ],
)
def test_malformed_bytes(data, error):
    with pytest.raises(error):
        decode(data)


def test_non_finite_command_velocity_rejected():
    body = body_of(encode(Command(seq=1, t_send_ns=1, action="arm_jog", velocity=(0.0,) * 6)))
    body["velocity"] = [0.0, math.inf, 0, 0, 0, 0]
    with pytest.raises(NonFiniteValueError):
        decode(rebuild(b"CMND", body))


@given(st.binary(max_size=300))
def test_random_bytes_never_escape_as_anything_but_decode_error(data):
    for topic in (b"STIM", b"HBRT", b"CMND", b"FRAM", b""):
        try:
            msg = decode(topic + data)
        except DecodeError:
            continue
        # Whatever decodes is valid by construction.
        if isinstance(msg, Stimulus):
            assert np.isfinite(msg.stimulus).all()


@given(st.integers(0, len(encode(stimulus())) - 1), st.integers(1, 255))
def test_any_single_byte_corruption_is_rejected_or_still_valid(index, flip):
    data = bytearray(encode(stimulus()))
    data[index] ^= flip
    try:
        msg = decode(bytes(data))
    except DecodeError:
        return
    assert isinstance(msg, Stimulus)
    assert np.isfinite(msg.stimulus).all() and msg.stimulus.min() >= 0
    assert ((msg.stimulus > 0).sum(axis=1) <= 1).all()


@pytest.mark.parametrize(
    ("extra", "error"),
    [
        ({"note": float("nan")}, NonFiniteValueError),
        ({"note": [1.0, {"deep": float("-inf")}]}, NonFiniteValueError),
        ({b"seq": 1}, FieldTypeError),
        ({"note": {b"k": 1}}, FieldTypeError),
        ({"note": [[[[[[[[[[1]]]]]]]]]]}, MalformedMessageError),
    ],
)
def test_unknown_keys_may_hold_nothing_the_protocol_forbids_anywhere(extra, error):
    body = body_of(encode(Command(seq=1, t_send_ns=2, action="arm_jog_end")))
    body.update(extra)
    with pytest.raises(error):
        decode(rebuild(b"CMND", body))
    body["action"] = "arm_stop"  # a stop is kept, its defect named
    stop = decode(rebuild(b"CMND", body))
    assert stop.action == "arm_stop" and stop.seq == 1 and len(stop.defects) == 1


@pytest.mark.parametrize(
    ("stamp", "defect"),
    [
        (float("nan"), "t_send_ns: command.t_send_ns must be an unsigned integer, not float"),
        ("soon", "t_send_ns: command.t_send_ns must be an unsigned integer, not str"),
        (2**64 - 1, "t_send_ns: command.t_send_ns = 18446744073709551615 is outside 0..2**63-1"),
        (None, "t_send_ns: missing"),
    ],
)
def test_a_stop_with_a_malformed_stamp_decodes_and_names_it_and_nothing_else_does(stamp, defect):
    signer = Signer.generate()
    for action in ("arm_stop", "arm_jog_end"):
        data = encode(Command(seq=4, t_send_ns=2, action=action, session=3), signer=signer)
        body = body_of(data)
        body.pop("sig")
        if stamp is None:
            body.pop("t_send_ns")
        else:
            body["t_send_ns"] = stamp
        resigned = _resign(body, signer)
        if action != "arm_stop":
            with pytest.raises(DecodeError):
                decode(resigned)
            continue
        stop = decode(resigned)
        assert (stop.seq, stop.t_send_ns, stop.session, stop.defects) == (4, 0, 3, (defect,))
        assert stop.signer == signer.public
        forged = resigned[:-1] + bytes([resigned[-1] ^ 1])
        with pytest.raises(SignatureError):  # a stop is kept, never a forged one
            decode(forged)


def _resign(body: dict, signer) -> bytes:
    """``body`` signed as ``encode`` signs (the sig entry last, over every byte before it)."""
    packed = rebuild(b"CMND", dict(body, sig=bytes(64)))
    signed = packed[:-SIG_ENTRY_BYTES]
    return signed + SIG_TAG + signer.sign(signed)


def test_a_multipart_message_is_refused_and_counted_by_the_subscriber():
    import time

    import zmq

    from common.wire.transport import Subscriber

    ctx = zmq.Context()
    sub = Subscriber(ctx, "tcp://127.0.0.1:*", bind=True)
    pub = ctx.socket(zmq.PUB)
    pub.setsockopt(zmq.LINGER, 0)
    pub.connect(sub.endpoint)
    try:
        good = encode(Command(seq=1, t_send_ns=2, action="arm_stop"))
        deadline = time.monotonic() + 5
        got = []
        while not got and time.monotonic() < deadline:
            pub.send_multipart([good, b"trailer"])
            pub.send(good)
            sub.poll(0.05)
            got = sub.drain()
        assert got and all(isinstance(m, Command) for m, _ in got)
        assert sub.rejected["MultipartMessageError"] >= 1
    finally:
        pub.close(0)
        sub.close()
        ctx.term()
