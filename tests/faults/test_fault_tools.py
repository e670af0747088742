"""The fault matrix's tools, each on its own: systemd's restart rule, a gripper's cable, a
recorder's file cut by a kill, a simulator's front panel and cable signals."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time

import pytest

from common.wire.codec import encode
from common.wire.messages import Heartbeat
from deploy.units.policy import policy
from harness.faults.matrix import ARM_UNREADABLE_S, first_unreadable
from harness.faults.probes import Sample
from operator_side.record_cli import _RECORD, read_records
from robot_side.gripper.sim import GripperSimServer


def test_restart_policy_is_the_shipped_units():
    robot, router = policy("robot"), policy("router")
    assert (robot.restart, robot.restart_sec, robot.watchdog_sec) == ("on-failure", 3.0, 5.0)
    assert (router.restart, router.restart_sec) == ("always", 0.5)
    assert robot.restarts_after(-signal.SIGKILL) and robot.restarts_after(-signal.SIGABRT)
    assert robot.restarts_after(1)
    assert not robot.restarts_after(0) and not robot.restarts_after(-signal.SIGTERM)
    assert policy("recorder") is None  # no unit ships: nobody restarts it


@pytest.mark.slow
def test_an_unplugged_gripper_refuses_and_comes_back_holding():
    with GripperSimServer() as sim:
        sim.model.write(ACT=1)
        time.sleep(0.5)
        sim.model.write(GTO=1, POS=220, SPE=255, FOR=100)
        time.sleep(0.6)
        held = sim.model.read()["POS"]
        client = socket.create_connection((sim.host, sim.port), timeout=5)
        sim.unplug()
        # the open connection is gone: closed, or reset when the close races a read
        with contextlib.suppress(ConnectionResetError):
            assert client.recv(16) == b""
        with pytest.raises(OSError):
            socket.create_connection((sim.host, sim.port), timeout=1)
        sim.replug()
        with socket.create_connection((sim.host, sim.port), timeout=5) as again:
            again.sendall(b"GET POS\n")
            assert again.recv(64).decode().split() == ["POS", str(held)]
        client.close()


def test_a_recording_cut_mid_record_reads_back_to_the_cut(tmp_path):
    path = tmp_path / "rec.bin"
    frames = [
        encode(Heartbeat(seq=i, t_send_ns=i, node="robot", state="ok"), b"cell1") for i in range(3)
    ]
    data = b"".join(_RECORD.pack(100 + i, len(f)) + f for i, f in enumerate(frames))
    path.write_bytes(data[:-5])  # a kill -9 in the middle of the last write
    got = list(read_records(path))
    assert [(t, name, msg.seq) for t, name, msg in got] == [(100, b"cell1", 0), (101, b"cell1", 1)]


def test_a_simulator_shows_its_front_panel_and_unplugs_on_a_signal(tmp_path):
    status = tmp_path / "servos.json"
    proc = subprocess.Popen(
        [sys.executable, "-m", "deploy.cli", "sim", "servos", "--status-file", str(status)],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        port = json.loads(proc.stdout.readline())["port"]
        deadline = time.monotonic() + 10
        while not status.exists() and time.monotonic() < deadline:
            time.sleep(0.02)
        panel = json.loads(status.read_text())
        assert panel["goals"] == {str(i): 2048 for i in range(1, 7)}
        proc.send_signal(signal.SIGUSR1)
        deadline = time.monotonic() + 5
        while os.path.exists(port) and time.monotonic() < deadline:
            time.sleep(0.02)
        assert not os.path.exists(port), "SIGUSR1 did not unplug the bus"
        proc.send_signal(signal.SIGUSR2)
        deadline = time.monotonic() + 5
        while not os.path.exists(port) and time.monotonic() < deadline:
            time.sleep(0.02)
        assert os.path.exists(port), "SIGUSR2 did not plug the bus back in"
    finally:
        proc.terminate()
        proc.wait(10)


def test_a_panel_written_late_still_lists_every_goal_since_the_one_before():
    """A simulator starved past the log's span writes its next panel with every goal written
    since its previous panel, not only the span's."""
    from collections import deque

    from deploy.sim_cli import GOAL_LOG_SPAN_NS, front_panel

    class Bus:
        def __init__(self, entries):
            self.goal_log = deque(entries)

    now = time.monotonic_ns()
    previous = now - 3 * GOAL_LOG_SPAN_NS  # the last panel, long ago
    old, recent = [previous + 1_000, 1, 100], [now - 1_000, 1, 200]
    assert front_panel(Bus([old, recent]))["goal_log"] == [recent]
    assert front_panel(Bus([old, recent]), previous)["goal_log"] == [old, recent]


def test_a_controller_that_stops_answering_is_away_from_its_last_reading():
    """A killed UR simulator gives no readings: that is the controller away, from the last one.

    Read as samples alone, the gap had passed for an arm that kept following the jog.
    """
    moving = [Sample(i * 0.01, 0.02) for i in range(100)]  # to 0.99 s
    back = [Sample(3.0 + i * 0.01, 0.0) for i in range(50)]  # a new controller from 3 s
    assert first_unreadable(moving + back, 0.5, 3.5) == pytest.approx(0.99)
    assert first_unreadable(moving, 0.5, 0.99 + ARM_UNREADABLE_S / 2) is None  # not yet
    assert first_unreadable(moving, 0.5, 0.99 + ARM_UNREADABLE_S) == pytest.approx(0.99)
    assert first_unreadable(back, 0.5, 3.5) == 0.5  # nothing at all since the fault
    steady = [Sample(i * 0.01, 0.02) for i in range(400)]
    assert first_unreadable(steady, 0.5, 3.99) is None
