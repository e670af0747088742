"""A captured signed stimulus, replayed through the relay: refused, counted, the palm unmoved.

Real processes: the relay, robot cell1 signing its stream, an observer's
operator node holding cell1's public key and driving a Feetech bus simulated
on a pty in this process (its goal registers are what the palm would do).
The attacker is raw pyzmq beside them: it reads the stream with a roster
key and injects with the robot's own CURVE key, as a compromised relay (or
anything else on the path) could. The robot is restarted in the middle: its
new run is believed, and the first run's stimulus is refused after it.
"""

from __future__ import annotations

import time

import pytest
import zmq

from common.codec import decode_named, name_prefix
from common.security import SecurityConfig, client_options
from deploy.fleet import SCRIPTED_TACTILE, Fleet
from operator_side.servos.sts_sim import FakeStsBus

pytestmark = [pytest.mark.slow, pytest.mark.timeout(240), pytest.mark.parallel]

BELIEVED = "believed: a heartbeat answered ours"
#: the fleet's held grasp without read noise, and the renderer's default dead band: once the
#: grip is steady the robot sends only keyframes, the palm rests, and any goal written is news
HELD_GRASP = (
    SCRIPTED_TACTILE.replace("deadband_n = 0.0\n", "")
    + "[robot.tactile.generator]\nnoise_n = 0.0\nnoise_relative = 0.0\n"
)


def _raw(ctx: zmq.Context, kind: int, endpoint: str, security: dict) -> zmq.Socket:
    sock = ctx.socket(kind)
    sock.setsockopt(zmq.LINGER, 0)
    for opt, value in client_options(SecurityConfig(**security)).items():
        sock.setsockopt(opt, value)
    sock.connect(endpoint)
    return sock


def _goals(palm: FakeStsBus) -> dict[int, int]:
    return {sid: palm.goal(sid) for sid in palm.config.ids}


def _settled(palm: FakeStsBus, quiet_s: float = 0.6, timeout_s: float = 20.0) -> int:
    """Wait until the operator has written no goal for ``quiet_s``; how many it wrote."""
    end = time.monotonic() + timeout_s
    n = len(palm.goal_log)
    while time.monotonic() < end:
        time.sleep(quiet_s)
        if len(palm.goal_log) == n:
            return n
        n = len(palm.goal_log)
    raise AssertionError(f"the palm never came to rest in {timeout_s} s")


def _newest_stimulus(spy: zmq.Socket, timeout_s: float = 5.0) -> bytes:
    """The newest STIM frame on the wire (drained for a keyframe's interval)."""
    newest, end = None, time.monotonic() + timeout_s
    while time.monotonic() < end and (newest is None or spy.poll(600)):
        if spy.poll(100):
            newest = spy.recv()
    assert newest is not None, "no stimulus on the wire"
    return newest


def test_a_replayed_signed_stimulus_is_refused_and_a_restarted_robot_is_believed(
    tmp_path, quiet_gc
):
    fleet = Fleet(
        robots=["cell1"], operators={"obs1": "observer", "spy": "observer"}, workdir=tmp_path
    )
    ctx = zmq.Context()
    with FakeStsBus() as palm, fleet:
        fleet.start_relay()
        fleet.start_robot("cell1", None, devices=HELD_GRASP)
        op = fleet.start_operator(
            "obs1",
            "cell1",
            want_frames=False,
            # the simulated bus answers from this (busy) test process: patient, like a slow adapter
            servos=f'kind = "feetech"\nport = "{palm.port}"\nreply_timeout_ms = 200.0\nretries = 5',
            # a loaded machine confirms the held grasp late and the palm would flicker; the
            # replayed stimulus, over a second old, stays stale by this rule all the same
            extra=["--set", "link.stale_after_ms=800"],
        )
        spy = _raw(ctx, zmq.SUB, fleet.ops_telemetry, fleet.client_security("spy"))
        spy.setsockopt(zmq.SUBSCRIBE, name_prefix(b"STIM", b"cell1"))
        injector = _raw(ctx, zmq.PUB, fleet.robots_telemetry, fleet.client_security("cell1"))
        try:
            fleet.wait_for(lambda: BELIEVED in op.log_text(), 60, "the robot's run believed")
            fleet.wait_for(lambda: "link down -> ok" in op.log_text(), 20, "the palm pressed")
            _settled(palm)
            pressed = _goals(palm)

            captured = _newest_stimulus(spy)
            name, msg = decode_named(captured)  # a real one: the robot's key signed it
            assert name == b"cell1" and msg.signer == fleet.signing_key("cell1")
            assert msg.session is not None
            time.sleep(1.0)
            writes = _settled(palm)
            injector.send(captured)
            fleet.wait_for(
                lambda: "Stimulus telemetry_replayed" in op.log_text(), 10, "the replay refused"
            )
            assert _settled(palm) == writes and _goals(palm) == pressed, "the palm moved"

            # the robot node restarts: a new run, its seqs from 1 again
            fleet.stop("cell1")
            fleet.wait_for(lambda: _goals(palm) != pressed, 10, "the palm lifted")
            _settled(palm)
            lifted = _goals(palm)
            fleet.start_robot("cell1", None, devices=HELD_GRASP)
            fleet.wait_for(
                lambda: op.log_text().count(BELIEVED) == 2 and "retired" in op.log_text(),
                60,
                "the restarted robot's run believed",
            )
            fleet.wait_for(
                lambda: op.log_text().count("-> ok") == 2, 20, "the new run's stimuli rendered"
            )
            # a node just started is slow for a few seconds (imports, first compiles): its
            # confirmations come late and the palm flickers until it has warmed up
            writes = _settled(palm, quiet_s=2.0, timeout_s=40.0)
            pressed = _goals(palm)
            assert pressed != lifted, "the restarted robot's grasp presses the palm again"
            injector.send(captured)  # the first run's stimulus, after the second run began
            fleet.wait_for(
                lambda: "Stimulus telemetry_old_session" in op.log_text(),
                10,
                "the earlier run's stimulus refused",
            )
            assert _settled(palm) == writes and _goals(palm) == pressed, "the palm moved"
        finally:
            spy.close()
            injector.close()
        fleet.stop("obs1@cell1")
        fleet.stop("cell1")
    ctx.term()
    stats = op.stats()
    assert stats.get("telemetry_replayed", 0) >= 1, stats
    assert stats.get("telemetry_old_session", 0) >= 1, stats
    assert stats.get("telemetry_sessions") == 2, stats
    assert stats.get("stimuli_received", 0) > 10, stats
