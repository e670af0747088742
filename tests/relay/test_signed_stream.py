"""A signed robot stream through the relay: a forger the relay lets in cannot reach a palm.

The forger holds the robot's CURVE key (so the relay accepts its telemetry,
as a compromised relay could inject its own) but not the robot's signing
key. Real processes: the relay, the robot signing its stream, an observer's
operator node holding the robot's public key.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
import zmq

from common.messages import Stimulus
from common.security import SecurityConfig, client_options
from common.signing import Signer
from common.transport import Publisher
from deploy.fleet import Fleet

pytestmark = [pytest.mark.slow, pytest.mark.timeout(120), pytest.mark.parallel]


def test_forged_stimuli_are_dropped_and_the_robots_own_still_arrive(tmp_path, quiet_gc):
    fleet = Fleet(robots=["cell1"], operators={"obs1": "observer"}, workdir=tmp_path)
    ctx = zmq.Context()
    with fleet:
        fleet.start_relay()
        fleet.start_robot("cell1", None)
        observer = fleet.start_operator("obs1", "cell1", want_frames=False)
        fleet.wait_for(lambda: "operator node up" in observer.log_text(), 30, "the operator")
        forger = Publisher(
            ctx,
            fleet.robots_telemetry,
            bind=False,
            sock_opts=client_options(SecurityConfig(**fleet.client_security("cell1"))),
            name=b"cell1",
            signer=Signer.generate(),  # a valid signature, by a key that is not the robot's
        )
        try:
            end, seq = time.monotonic() + 3.0, 10**6
            while time.monotonic() < end:
                seq += 1
                t = time.monotonic_ns()
                forger.send(
                    Stimulus(
                        seq=seq,
                        t_send_ns=t,
                        t_capture_ns=t,
                        frame_seq=seq,
                        mode="mask",
                        contact=True,
                        stimulus=np.eye(3, dtype=np.float32),  # a 135 deg band, well formed
                        pattern=3,
                    )
                )
                time.sleep(1 / 60)
        finally:
            forger.close()
        fleet.stop("obs1@cell1")
        fleet.stop("cell1")
    ctx.term()
    stats = observer.stats()
    assert stats.get("telemetry_forged", 0) > 60, stats  # nearly all of ~180 forged
    assert stats.get("stimuli_received", 0) > 60, stats  # the robot's own, all along
    assert "telemetry dropped: not signed by the robot's key" in observer.log_text()
