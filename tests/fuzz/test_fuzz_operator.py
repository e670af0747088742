"""Malformed messages at a running operator node's telemetry: 25,000 a run.

The node keeps running, keeps rendering a good stimulus stream sent in
between, counts every rejected message, and the servo bus never receives a
count outside the calibration (InMemoryServoBus refuses those, so its
refused counter must stay 0). Messages that the codec accepts even though
they were mutated are sent last: they may legitimately change what is
rendered, but never make anything unsafe.
"""

from __future__ import annotations

import collections
import time

import pytest
from fuzz_rigs import N_MALFORMED, MutantStream, OperatorRig, fuzz_seed
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from common.wire.codec import DecodeError, decode
from common.wire.codec_schema import WIRE_KEYS

pytestmark = pytest.mark.slow

PATTERNS = [6, 3, 9, None, 0, 7, 11, 4]
CHECKPOINT_TIMEOUT_S = 10.0  # generous: a shared CI machine can starve any thread
# the telemetry side mostly carries these; commands come too, from a confused peer
KINDS = ["stimulus", "stimulus", "frame", "heartbeat", "heartbeat", "command"]


@pytest.fixture(scope="module")
def rig():
    r = OperatorRig()
    r.start()
    yield r
    r.close()


def test_operator_survives_malformed_telemetry_and_keeps_rendering(rig):
    t0 = time.monotonic()
    # about 15% of mutants still decode; generate until N_MALFORMED rejected ones were sent
    stream = MutantStream(seed=fuzz_seed(606), total=2 * N_MALFORMED, kinds=KINDS)
    verdicts: collections.Counter[str] = collections.Counter()
    escaped, spec, valid = [], [], []
    base_rejected = rig.rejected()
    sent_bad = 0
    reached, missed = 0, []
    k = 0
    pending = None
    try:
        for batch in stream:
            for verdict, detail, data in batch:
                verdicts[verdict] += 1
                if verdict == "escaped":
                    escaped.append((detail, data))
                elif verdict == "spec":
                    spec.append((detail, data))
                elif verdict == "valid":
                    valid.append(data)
                elif verdict == "oversize":
                    pass  # tests/fuzz/test_fuzz_oversize.py: they cost the connection
                else:
                    verdicts[f"rejected:{detail}"] += 1
                    rig.send_raw(data)
                    sent_bad += 1
            assert rig.sync(), "the operator node stopped reading its socket"
            if sent_bad >= N_MALFORMED and pending is None:
                break
            assert rig.alive(), f"the operator node died: {rig.error}"
            # a good stimulus at a time; the next one only once the palm shows it
            if pending is None:
                msg = rig.show(PATTERNS[k % len(PATTERNS)])
                target = rig.node.renderer.target_counts(msg.stimulus if msg.contact else None)
                pending = (target, time.monotonic() + CHECKPOINT_TIMEOUT_S, msg)
                k += 1
            elif rig.goal_reached(pending[0]):
                reached += 1
                pending = None
            elif time.monotonic() > pending[1]:
                missed.append(pending[2])
                pending = None
    finally:
        stream.close()
    fuzz_s = time.monotonic() - t0
    assert not escaped, f"decode raised something other than DecodeError: {escaped[:3]}"
    assert not spec, f"decoded messages that break the protocol spec: {spec[:3]}"
    assert sent_bad >= N_MALFORMED
    assert rig.sync()
    assert rig.rejected() - base_rejected == sent_bad, "a rejected message was not counted"
    assert rig.node.counters["decode_errors"] == rig.rejected()
    assert reached >= 5 and not missed, f"{len(missed)} good stimuli never reached the palm"
    assert rig.servo_violations() == []
    print(
        f"\noperator: {sent_bad} rejected + {len(valid)} valid mutants generated, "
        f"{fuzz_s:.1f} s, {reached} good stimuli rendered in between; {dict(verdicts)}"
    )

    # mutants the codec accepts: anything may be rendered, nothing unsafe may happen
    for data in valid:
        rig.send_raw(data)
        if rig.sent % 500 == 0:
            assert rig.sync()
    assert rig.sync() and rig.alive()
    assert rig.servo_violations() == []
    assert rig.rejected() - base_rejected == sent_bad


# ---------------------------------------------------------------- hypothesis
_any_scalar = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**63), max_value=2**64 - 1),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=20),
    st.binary(max_size=64),
)
_value = st.recursive(
    _any_scalar,
    lambda inner: st.one_of(
        st.lists(inner, max_size=8), st.dictionaries(st.text(max_size=8), inner, max_size=8)
    ),
    max_leaves=20,
)
_FIELDS = [
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
    "frame",
    "node",
    "state",
    "stats",
    "echo_t_send_ns",
]


@st.composite
def telemetry_message(draw) -> bytes:
    """A topic and a map of protocol field names with values of any type, some right."""
    import msgpack

    topic = draw(st.sampled_from([b"STIM", b"FRAM", b"HBRT", b"CMND", b"JUNK"]))
    body = {"v": 1, "type": {b"STIM": "stimulus", b"FRAM": "frame"}.get(topic, "heartbeat")}
    for name in draw(st.lists(st.sampled_from(_FIELDS), max_size=10, unique=True)):
        body[name] = draw(_value)
    if draw(st.booleans()):  # as this version keys it; else as version 1 did
        body = {WIRE_KEYS.get(k, k): v for k, v in body.items() if k != "type"} | {"v": 2}
    try:
        return topic + msgpack.packb(body, use_bin_type=True)
    except (OverflowError, ValueError):
        return topic + b"\xc1"


@settings(
    max_examples=25,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
@given(batch=st.lists(telemetry_message(), min_size=1, max_size=40))
def test_operator_counts_every_hypothesis_message_it_rejects(rig, batch):
    assert rig.sync()
    before = rig.rejected()
    expected = 0
    for data in batch:
        try:
            decode(data)
        except DecodeError:
            expected += 1
            rig.send_raw(data)
    assert rig.sync() and rig.alive()
    assert rig.rejected() - before == expected
    assert rig.servo_violations() == []
