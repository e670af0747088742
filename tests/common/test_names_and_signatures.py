"""Robot names after the topic, and end-to-end signatures (docs/protocol.md)."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
import zmq

from common.wire.codec import (
    DecodeError,
    RobotNameError,
    SignatureError,
    check_robot_name,
    decode,
    decode_named,
    encode,
    name_prefix,
)
from common.wire.messages import Command, Heartbeat, Stimulus
from common.wire.signing import Signer
from common.wire.transport import Publisher, Subscriber


def _stim() -> Stimulus:
    cells = np.zeros((3, 3), np.float32)
    cells[0, 1] = 2.5
    return Stimulus(
        seq=3,
        t_send_ns=10,
        t_capture_ns=9,
        frame_seq=1,
        mode="direct",
        contact=True,
        stimulus=cells,
    )


def _jog(seq: int = 1) -> Command:
    return Command(seq=seq, t_send_ns=100 + seq, action="arm_jog", velocity=(0.01, 0, 0, 0, 0, 0))


def test_a_named_frame_round_trips_and_an_unnamed_one_is_a_bare_map_as_before():
    data = encode(_stim(), b"cell1")
    assert data.startswith(b"STIM\x05cell1")
    name, msg = decode_named(data)
    assert name == b"cell1" and msg.stimulus[0, 1] == pytest.approx(2.5)
    plain = encode(_stim())
    assert plain[4] in range(0x80, 0x90)  # a msgpack fixmap: never a name's length byte
    assert decode_named(plain)[0] == b"" and msgpack.unpackb(plain[4:])["v"] == 2


def test_a_prefix_selects_one_robot_only():
    assert not name_prefix(b"STIM", b"cell10").startswith(name_prefix(b"STIM", b"cell1"))


@pytest.mark.parametrize("bad", ["", "x" * 33, "cell 1", "cellé", "a/b"])
def test_a_name_the_protocol_forbids_is_refused(bad):
    with pytest.raises(RobotNameError):
        check_robot_name(bad)


def test_a_length_byte_that_overruns_or_a_forbidden_byte_is_a_named_error():
    with pytest.raises(DecodeError):
        decode(b"STIM\x05ce")
    with pytest.raises(RobotNameError):
        decode(b"STIM\x03c l" + msgpack.packb({"v": 1}))


def test_a_signed_command_verifies_and_names_its_signer():
    signer = Signer.generate()
    name, msg = decode_named(encode(_jog(), b"cell1", signer))
    assert name == b"cell1" and msg.signer == signer.public and msg.velocity[0] == 0.01


def test_every_tampering_is_caught():
    signer = Signer.generate()
    data = encode(_jog(), b"cell1", signer)
    # another robot's name: the signature covers the name, so a relay cannot redirect
    redirected = b"CMND\x05cell2" + data[len(b"CMND\x05cell1") :]
    with pytest.raises(SignatureError):
        decode(redirected)
    # a changed velocity, same length
    body = msgpack.unpackb(data[10:])
    assert body["u"][0] == 0.01  # u: the velocity on the wire
    i = data.index(msgpack.packb(0.01))
    changed = data[:i] + msgpack.packb(0.09) + data[i + 9 :]
    with pytest.raises(SignatureError):
        decode(changed)
    # another key's claim: the signer field swapped for an attacker's key
    mallory = Signer.generate()
    swapped = data.replace(signer.public, mallory.public)
    with pytest.raises(SignatureError):
        decode(swapped)
    # a signer without a signature, and a signature that is not the last entry
    unsigned = dict(body)
    del unsigned["sig"]
    with pytest.raises(SignatureError):
        decode(b"CMND\x05cell1" + msgpack.packb(unsigned))
    moved = {"sig": body["sig"], **unsigned}
    with pytest.raises(SignatureError):
        decode(b"CMND\x05cell1" + msgpack.packb(moved))


def test_a_subscriber_for_one_robot_refuses_another_robots_messages_and_counts_them():
    ctx = zmq.Context()
    try:
        pub = Publisher(ctx, "inproc://names", bind=True, name=b"cell2")
        sub = Subscriber(ctx, "inproc://names", bind=False, expect_name=b"cell1")
        import time

        time.sleep(0.05)
        pub.send(Heartbeat(seq=1, t_send_ns=1, node="robot", state="ok"))
        assert sub.poll(1.0)
        assert sub.drain() == [] and sub.rejected["WrongRobotError"] == 1
        pub.close()
        sub.close()
    finally:
        ctx.term()


def test_a_command_signed_exactly_as_the_protocol_doc_says_is_accepted():
    """docs/protocol.md, Signed messages: built with msgpack and cryptography only."""
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
    from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat

    key = Ed25519PrivateKey.generate()
    public = key.public_key().public_bytes(Encoding.Raw, PublicFormat.Raw)
    body = {
        "v": 1,
        "type": "command",
        "seq": 4,
        "t_send_ns": 99,
        "action": "arm_stop",
        "session": 5,
        "signer": public,
    }
    # the map header counts the sig entry that follows the signed bytes
    header = bytes((0x80 + len(body) + 1,))
    entries = msgpack.packb(body)[1:]  # drop packb's own fixmap header
    signed = b"CMND\x05cell1" + header + entries
    data = signed + b"\xa3sig\xc4\x40" + key.sign(signed)
    name, msg = decode_named(data)
    assert name == b"cell1" and msg.action == "arm_stop" and msg.signer == public


def test_a_heartbeat_from_an_older_build_names_its_lease_holder_under_the_old_field():
    """Builds before the rename sent the lease holder's key as ``controller``: a signed
    heartbeat of theirs still verifies and reads as ``lease_holder``; the new name wins."""
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
    from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat

    key = Ed25519PrivateKey.generate()
    public = key.public_key().public_bytes(Encoding.Raw, PublicFormat.Raw)
    holder = bytes(range(32))

    def signed_heartbeat(**fields) -> bytes:
        body = {"v": 1, "type": "heartbeat", "seq": 7, "t_send_ns": 70, "node": "robot"}
        body |= {"state": "ok", "signer": public, **fields}
        signed = b"HBRT" + bytes((0x80 + len(body) + 1,)) + msgpack.packb(body)[1:]
        return signed + b"\xa3sig\xc4\x40" + key.sign(signed)

    old = decode(signed_heartbeat(controller=holder))
    assert old.lease_holder == holder and old.signer == public
    both = decode(signed_heartbeat(controller=bytes(32), lease_holder=holder))
    assert both.lease_holder == holder
    new = Heartbeat(seq=1, t_send_ns=2, node="robot", state="ok", lease_holder=holder)
    assert b"\xa1h\xc4\x20" + holder in encode(new)  # version 2's key for lease_holder
    assert b"controller" not in encode(new)
    assert decode(encode(new)).lease_holder == holder
