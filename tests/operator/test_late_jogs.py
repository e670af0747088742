"""A jog that waited on a busy operator PC never reaches the robot; stops always do.

The "robot" here is the test: raw pyzmq sockets where the robot binds, its
heartbeats keeping the node's view of it fresh, and what arrives on its
command socket is what the robot would act on.
"""

from __future__ import annotations

import threading
import time

import pytest
import zmq

from common.clocks.clock import now_ns
from common.wire.codec import decode, encode
from common.wire.messages import Command, Heartbeat
from common.wire.transport import last_endpoint
from operator_side.node import OperatorNode
from operator_side.node.config import OperatorConfig
from operator_side.servos.in_memory import InMemoryServoBus

pytestmark = pytest.mark.timeout(30)

JOG = (0.02, 0.0, 0.0, 0.0, 0.0, 0.0)


class Robot:
    """The robot's two sockets, a 20 Hz heartbeat, and every command that arrives."""

    def __init__(self) -> None:
        self.ctx = zmq.Context()
        self.tel = self.ctx.socket(zmq.PUB)
        self.tel.bind("tcp://127.0.0.1:*")
        self.cmd = self.ctx.socket(zmq.SUB)
        self.cmd.setsockopt(zmq.SUBSCRIBE, b"")
        self.cmd.bind("tcp://127.0.0.1:*")
        self.commands: list[Command] = []
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        seq = 0
        while not self.stop.is_set():
            seq += 1
            self.tel.send(encode(Heartbeat(seq=seq, t_send_ns=now_ns(), node="robot", state="ok")))
            while self.cmd.poll(50):
                msg = decode(self.cmd.recv())
                if isinstance(msg, Command):
                    self.commands.append(msg)

    def actions(self) -> list[str]:
        return [c.action for c in self.commands]

    def close(self) -> None:
        self.stop.set()
        self.thread.join(5)
        self.tel.close(0)
        self.cmd.close(0)
        self.ctx.term()


@pytest.fixture
def linked():
    robot = Robot()
    config = OperatorConfig()
    config.link.telemetry_endpoint = last_endpoint(robot.tel)
    config.link.command_endpoint = last_endpoint(robot.cmd)
    node = OperatorNode(config, InMemoryServoBus())
    stop = threading.Event()
    thread = threading.Thread(target=node.run, args=(stop,), daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + 10
        # both directions up: the node hears heartbeats and the robot hears the node's
        while not (node.sees_robot(now_ns()) and robot.commands):
            assert time.monotonic() < deadline, "the link never came up"
            node.send_command("arm_jog_end")
            time.sleep(0.05)
        robot.commands.clear()
        yield node, robot
    finally:
        stop.set()
        thread.join(10)
        robot.close()


def wait_for_actions(robot: Robot, n: int, timeout_s: float = 5.0) -> list[str]:
    deadline = time.monotonic() + timeout_s
    while len(robot.commands) < n and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(0.1)  # and nothing more after them
    return robot.actions()


def test_a_jog_older_than_the_limit_is_dropped_and_a_fresh_one_goes(linked):
    node, robot = linked
    limit = node.config.link.jog_max_age_ms
    node.send_command("arm_jog", velocity=JOG, age_ms=limit + 50)  # the hand let go since
    node.send_command("arm_assist", age_ms=limit + 50)
    node.send_command("arm_jog_end", age_ms=limit + 50)  # ends and stops are never dropped
    node.send_command("arm_jog", velocity=JOG, age_ms=limit / 3)
    node.send_command("arm_jog", velocity=JOG, age_ms=float("nan"))  # no age to trust: too old
    assert wait_for_actions(robot, 2) == ["arm_jog_end", "arm_jog"]
    assert node.counters["jogs_dropped_late"] == 3
    assert node.counters["jogs_held_blind"] == 0


def test_jogs_queued_behind_a_starved_loop_are_dropped(linked):
    """The node's own loop falls silent (starved) while the dashboard queues jogs."""
    node, robot = linked
    limit_s = node.config.link.jog_max_age_ms / 1000
    stalled = threading.Event()
    release = threading.Event()
    real_flush = node.flush_commands

    def starved_flush(now: int) -> None:
        if stalled.is_set():
            release.wait(5)  # the loop thread is stuck here, as if it got no CPU
            stalled.clear()
            now = node.now()  # it wakes later: its clock has moved on
        real_flush(now)

    node.flush_commands = starved_flush
    stalled.set()
    node.send_command("arm_jog", velocity=JOG)
    time.sleep(0.1)  # the loop wakes for it and stalls
    for _ in range(5):
        node.send_command("arm_jog", velocity=JOG)
        time.sleep(0.033)
    time.sleep(limit_s)
    node.send_command("arm_jog_end")
    release.set()
    deadline = time.monotonic() + 5
    while not node.sees_robot(now_ns()):  # awake, it reads the robot again
        assert time.monotonic() < deadline
        time.sleep(0.01)
    node.send_command("arm_jog", velocity=JOG)  # the hand, now
    assert wait_for_actions(robot, 2) == ["arm_jog_end", "arm_jog"]
    assert node.counters["jogs_dropped_late"] == 6


def test_a_stdin_jog_that_waited_in_the_pipe_is_dropped(linked, monkeypatch, caplog):
    """``--commands-from-stdin``: the writer's monotonic time says how long a line waited."""
    import io
    import json

    from operator_side.node_cli import StdinCommands

    node, robot = linked
    waited_s = 2 * node.config.link.jog_max_age_ms / 1000
    lines = [
        {"action": "arm_jog", "velocity": list(JOG), "issued_monotonic_s": time.monotonic() - 1},
        {"action": "arm_jog", "velocity": list(JOG), "issued_monotonic_s": "nan"},
        {"action": "arm_jog_end", "issued_monotonic_s": time.monotonic() - waited_s},
        {"action": "arm_jog", "velocity": list(JOG), "issued_monotonic_s": time.monotonic()},
        {"action": "arm_jog", "velocity": list(JOG)},  # says nothing: as fresh as it is read
    ]
    monkeypatch.setattr("sys.stdin", io.StringIO("".join(json.dumps(c) + "\n" for c in lines)))
    StdinCommands(node)
    assert wait_for_actions(robot, 3) == ["arm_jog_end", "arm_jog", "arm_jog"]
    assert node.counters["jogs_dropped_late"] == 1
    assert "issued_monotonic_s must be a finite number" in caplog.text
