"""Malformed messages at a running robot node's command socket: 25,000 a run.

The fuzz comes from its own connection, as a stranger's would, beside a
good operator that keeps sending heartbeats and commands. The node keeps
running, keeps publishing stimuli, keeps answering the good heartbeats and
applying the good commands, counts every rejected message, and the gripper
and arm drivers only ever receive finite values inside their limits:
mutated commands the codec accepts (a jog at 1e308 m/s is still a finite
number) are sent too, and must be clipped by the devices' safety layer.
"""

from __future__ import annotations

import collections
import time

import numpy as np
import pytest
from fuzz_rigs import (
    N_MALFORMED,
    MutantStream,
    RobotRig,
    arm_violations,
    fuzz_seed,
    gripper_violations,
    wait_for,
)
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from common.wire.codec import DecodeError, decode
from common.wire.codec_schema import WIRE_KEYS
from common.wire.messages import Command

pytestmark = pytest.mark.slow

KINDS = ["command", "command", "command", "heartbeat", "heartbeat", "stimulus"]
CHECK_EVERY_BATCHES = 10


@pytest.fixture(scope="module")
def rig():
    r = RobotRig()
    r.start()
    yield r
    r.close()


def _check_good_commands(rig: RobotRig, k: int) -> None:
    """With the fuzz paused: a good close and a good jog are applied, exactly."""
    level = 1 + k % 31
    velocity = (0.01 * ((k % 5) - 2), 0.02, 0.0, 0.0, 0.0, 0.1)
    rig.command("gripper_close", grip_level=level)
    # a mutant arm_stop that decodes is a STOP and latches the arm: the operator resumes
    rig.command("arm_resume")
    rig.command("arm_jog", velocity=velocity)
    assert rig.sync(), "the robot node stopped reading its socket"

    def applied() -> bool:  # read is not applied: the node acts after draining its socket
        jogs, grips = rig.arm.sent_jogs, rig.gripper.commands
        return (
            bool(jogs and grips)
            and grips[-1][0] == rig.gripper.levels.position(level)
            and np.allclose(jogs[-1], velocity)
        )

    assert wait_for(applied, 2), "a good command was read but not applied"


# A jog of 1e308 m/s overflows the norm in Arm.clip_jog to inf; the scale then is 0 and the
# arm stops: safe, and the warning says so.
@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")
def test_robot_survives_malformed_commands_and_keeps_serving(rig):
    t0 = time.monotonic()
    stream = MutantStream(seed=fuzz_seed(707), total=2 * N_MALFORMED, kinds=KINDS)
    verdicts: collections.Counter[str] = collections.Counter()
    escaped, spec, later = [], [], []
    base_rejected = rig.rejected()
    base_cmds = rig.node.counters["commands_received"]
    base_stimuli = rig.telemetry["stimulus"]
    sent_bad = sent_valid_cmds = good_cmds = checks = 0
    try:
        for n, batch in enumerate(stream):
            for verdict, detail, data in batch:
                verdicts[verdict] += 1
                if verdict == "escaped":
                    escaped.append((detail, data))
                elif verdict == "spec":
                    spec.append((detail, data))
                elif verdict == "oversize":
                    pass  # tests/fuzz/test_fuzz_oversize.py
                elif verdict == "valid":
                    if isinstance(decode(data), Command):
                        rig.send_evil(data)  # the devices' limits must hold
                        sent_valid_cmds += 1
                    else:
                        later.append(data)
                else:
                    verdicts[f"rejected:{detail}"] += 1
                    rig.send_evil(data)
                    sent_bad += 1
            rig.read_telemetry()
            assert rig.sync(), "the robot node stopped reading its socket"
            assert rig.alive(), f"the robot node died: {rig.error}"
            if n % CHECK_EVERY_BATCHES == 0:
                _check_good_commands(rig, checks)
                good_cmds += 3  # a close, a resume, a jog
                checks += 1
            if sent_bad >= N_MALFORMED:
                break
    finally:
        stream.close()
    fuzz_s = time.monotonic() - t0
    rig.read_telemetry()
    assert rig.sync()
    assert not escaped, f"decode raised something other than DecodeError: {escaped[:3]}"
    assert not spec, f"decoded messages that break the protocol spec: {spec[:3]}"
    assert sent_bad >= N_MALFORMED
    assert rig.rejected() - base_rejected == sent_bad, "a rejected message was not counted"
    received_cmds = rig.node.counters["commands_received"] - base_cmds
    assert received_cmds == good_cmds + sent_valid_cmds
    assert arm_violations(rig.arm) == [] and gripper_violations(rig.gripper) == []
    # it kept publishing and answering our heartbeats all along
    assert wait_for(lambda: (rig.read_telemetry(), rig.echoed)[1] > 0, 2)
    assert rig.telemetry["stimulus"] > base_stimuli
    # a starved machine may trip the deadman (correctly); the link must come back by itself
    assert wait_for(lambda: rig.node.link_state == "ok", 2), "the operator link did not recover"
    trips = rig.node.counters["deadman_trips"]
    print(
        f"\nrobot: {sent_bad} rejected + {sent_valid_cmds} valid-but-mutated commands in "
        f"{fuzz_s:.1f} s, {checks} good-command checks, {rig.echoed} heartbeats echoed, "
        f"{trips} deadman trips; "
        f"{dict(verdicts)}"
    )

    # the rest of what decodes (heartbeats, telemetry types): nothing unsafe, still serving
    for i, data in enumerate(later):
        rig.send_evil(data)
        if i % 500 == 0:
            rig.read_telemetry()
            assert rig.sync()
    assert rig.sync() and rig.alive()
    _check_good_commands(rig, checks + 1)
    assert arm_violations(rig.arm) == [] and gripper_violations(rig.gripper) == []
    assert rig.rejected() - base_rejected == sent_bad


@st.composite
def command_message(draw) -> bytes:
    """A CMND map with the command's fields holding values of any type, some right."""
    import msgpack

    scalar = st.one_of(
        st.none(),
        st.booleans(),
        st.integers(min_value=-(2**63), max_value=2**64 - 1),
        st.floats(),
        st.text(max_size=12),
        st.binary(max_size=16),
    )
    body = {
        "v": draw(st.sampled_from([1, 2, 2, 2, 0, 3, "1", None])),
        "type": draw(st.sampled_from(["command", "command", "heartbeat", "", None])),
        "seq": draw(st.one_of(st.integers(min_value=0, max_value=2**63 - 1), scalar)),
        "t_send_ns": draw(st.one_of(st.integers(min_value=0, max_value=2**63 - 1), scalar)),
        "action": draw(st.one_of(st.sampled_from(["arm_jog", "gripper_close", "x"]), scalar)),
        "grip_level": draw(st.one_of(st.integers(min_value=-5, max_value=40), scalar)),
        "velocity": draw(
            st.one_of(st.lists(st.one_of(st.floats(), scalar), min_size=5, max_size=7), scalar)
        ),
    }
    for key in draw(st.lists(st.sampled_from(sorted(body)), max_size=3, unique=True)):
        del body[key]
    if body.get("v") != 1:  # version 2's keys
        body = {WIRE_KEYS.get(k, k): v for k, v in body.items()}
    try:
        return b"CMND" + msgpack.packb(body, use_bin_type=True)
    except (OverflowError, ValueError):
        return b"CMND\xc1"


@settings(
    max_examples=25,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
@given(batch=st.lists(command_message(), min_size=1, max_size=40))
def test_robot_obeys_only_commands_that_decode(rig, batch):
    assert rig.sync()
    before_rejected = rig.rejected()
    before_cmds = rig.node.counters["commands_received"]
    expected_rejected = expected_cmds = 0
    for data in batch:
        try:
            decode(data)
        except DecodeError:
            expected_rejected += 1
        else:
            expected_cmds += 1
        rig.send_evil(data)
    rig.read_telemetry()
    assert rig.sync() and rig.alive()
    assert rig.rejected() - before_rejected == expected_rejected
    assert rig.node.counters["commands_received"] - before_cmds == expected_cmds
    assert arm_violations(rig.arm) == [] and gripper_violations(rig.gripper) == []
