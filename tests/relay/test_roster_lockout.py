"""A roster reload that would lock the fleet out is refused, and the fleet keeps working.

A real relay process re-reads its roster on SIGHUP while a robot key's
stimuli flow to an observer and a controller's commands flow to the robot
key; what flows is judged at those clients, outside the relay.
"""

from __future__ import annotations

import json
import signal
import threading
import time

import numpy as np
import pytest
import zmq

from common.codec import encode, name_prefix
from common.messages import Command, Stimulus
from common.security import SecurityConfig, client_options
from deploy.fleet import Fleet

pytestmark = [pytest.mark.slow, pytest.mark.timeout(90), pytest.mark.parallel]


class _Traffic:
    """cell1's stimuli to obs and alice's commands to cell1 at 100 Hz, counted where they land."""

    def __init__(self, fleet: Fleet) -> None:
        self.ctx = zmq.Context()
        self.fleet = fleet
        self.stimuli = 0
        self.commands = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def socket(self, kind: int, member: str, endpoint: str, topic: bytes | None = None):
        sock = self.ctx.socket(kind)
        sock.setsockopt(zmq.LINGER, 0)
        security = SecurityConfig(**self.fleet.client_security(member))
        for opt, value in client_options(security).items():
            sock.setsockopt(opt, value)
        if topic is not None:
            sock.setsockopt(zmq.SUBSCRIBE, topic)
        sock.connect(endpoint)
        return sock

    def _run(self) -> None:
        f = self.fleet
        robot_pub = self.socket(zmq.PUB, "cell1", f.robots_telemetry)
        robot_sub = self.socket(
            zmq.SUB, "cell1", f.robots_command, name_prefix(Command.TOPIC, b"cell1")
        )
        obs = self.socket(zmq.SUB, "obs", f.ops_telemetry, name_prefix(Stimulus.TOPIC, b"cell1"))
        alice = self.socket(zmq.PUB, "alice", f.ops_command)
        seq = 0
        while not self._stop.is_set():
            seq += 1
            t = time.monotonic_ns()
            stimulus = Stimulus(seq, t, t, seq, "mask", True, np.eye(3, dtype=np.float32), 3)
            robot_pub.send(encode(stimulus, b"cell1"))
            alice.send(encode(Command(seq, t, "gripper_open"), b"cell1"))
            time.sleep(0.01)
            while obs.poll(0):
                obs.recv()
                self.stimuli += 1
            while robot_sub.poll(0):
                robot_sub.recv()
                self.commands += 1
        for sock in (robot_pub, robot_sub, obs, alice):
            sock.close(0)

    def counts_grow(self, seconds: float) -> tuple[int, int]:
        """How many stimuli and commands arrived over the next ``seconds``."""
        s0, c0 = self.stimuli, self.commands
        time.sleep(seconds)
        return self.stimuli - s0, self.commands - c0

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self.ctx.term()


def _reload(fleet: Fleet, text: str, verdict: str) -> None:
    """Put ``text`` in place as the roster (atomically), SIGHUP the relay, wait for ``verdict``
    to appear once more in its log."""
    relay = fleet.procs["relay"]
    before = relay.log_text().count(verdict)
    tmp = fleet.roster.with_suffix(".new")
    tmp.write_text(text)
    tmp.replace(fleet.roster)
    relay.popen.send_signal(signal.SIGHUP)
    fleet.wait_for(lambda: relay.log_text().count(verdict) > before, 10, verdict)


def test_an_empty_and_a_truncated_roster_are_refused_and_the_fleet_keeps_working(tmp_path):
    fleet = Fleet(
        robots=["cell1"], operators={"alice": "controller", "obs": "observer"}, workdir=tmp_path
    )
    good = fleet.roster.read_text()
    truncated = good[: good.index("[[robot]]")]  # cut at an entry boundary: operators only
    status = tmp_path / "relay-roster-status.json"
    with fleet:
        relay = fleet.start_relay()
        fleet.wait_for(lambda: "relay up" in relay.log_text(), 30, "the relay")
        traffic = _Traffic(fleet)
        try:
            fleet.wait_for(lambda: traffic.stimuli and traffic.commands, 20, "the fleet's flow")
            _reload(fleet, "", "roster reload failed")
            assert "would remove every robot (1) and every controller (alice)" in relay.log_text()
            _reload(fleet, truncated, "roster reload failed")
            assert "would remove every robot (1): an empty or truncated" in relay.log_text()
            refused = json.loads(status.read_text())["refused"]["reason"]
            assert "would remove every robot" in refused, refused
            stimuli, commands = traffic.counts_grow(1.0)
            assert stimuli > 40 and commands > 40, (stimuli, commands)
            # a key connecting now still gets in: the allowlist in force is the old one
            late = traffic.socket(
                zmq.SUB, "cell1", fleet.robots_command, name_prefix(Command.TOPIC, b"cell1")
            )
            assert late.poll(5000), "a robot key connecting after the refused reloads"
            late.close(0)

            # the control: the file's own word lets the same lockout through
            _reload(fleet, "allow_lockout = true\n" + truncated, "closing every connection")
            time.sleep(0.3)  # what was in flight when the relay closed has landed
            cut_off = traffic.counts_grow(1.0)
        finally:
            traffic.close()
        fleet.stop("relay")
    assert cut_off == (0, 0), f"the forced lockout let {cut_off} through"
    stats = relay.stats()
    assert stats["roster_reloads_refused"] == 2, stats
    assert stats["roster_reloads"] == 1 and stats["reopens"] == 1, stats
