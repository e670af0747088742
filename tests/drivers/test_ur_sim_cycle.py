"""The UR simulator's cycle on a loaded machine: packages by the clock, and its own lag excused.

A controller is hard real time; the simulator's cycle runs late when the
machine is busy. What a late cycle must not do is make the client look
silent: packages go out by the wall clock (a late tick sends what is due),
and while the client waits for a script state the simulator has set but not
yet sent, its silence is the simulator's (unless the stream is frozen on
purpose, a held-back network).
"""

from __future__ import annotations

import os
import socket
import struct
from pathlib import Path

import pytest
from tests_support import ManualClock, fifo_granted

from harness.processes import thread_policies
from robot_side.arm.sim import URSimProcess, rtde_server
from robot_side.arm.sim.commands import STATUS_DONE, STATUS_READY
from robot_side.arm.sim.rtde_server import RTDEConnection
from robot_side.arm.sim.server import URSimConfig, URSimulator


@pytest.fixture
def rig(monkeypatch):
    clock = ManualClock()
    monkeypatch.setattr(rtde_server, "now_s", clock)
    sim = URSimulator(URSimConfig())  # never started: its parts only
    a, b = socket.socketpair()
    conn = RTDEConnection(a, "client")
    conn.started = True
    conn.output = (1, ["output_int_register_0"], ["INT32"], struct.Struct(">i"))
    conn.output_period_s = 0.008  # ur-rtde's 125 Hz
    conn.status_at = 0
    conn.inputs = {1: (["input_int_register_0"], ["INT32"], struct.Struct(">i"))}
    sim.rtde.conns.append(conn)
    yield sim, conn, clock
    a.close()
    b.close()


def test_packages_go_out_by_the_clock_and_a_late_tick_sends_at_once(rig):
    sim, conn, clock = rig
    assert sim.rtde.due() == [conn]
    clock.t += 0.002
    assert sim.rtde.due() == []  # a 2 ms tick: not yet
    clock.t += 0.006
    assert sim.rtde.due() == [conn]
    clock.t += 0.1  # a tick 100 ms late (ticks counted, it was one of four)
    assert sim.rtde.due() == [conn]
    clock.t += 0.002
    assert sim.rtde.due() == [], "a late tick must not be followed by a burst"
    clock.t += 0.006
    assert sim.rtde.due() == [conn]


def test_a_state_set_and_not_yet_sent_excuses_the_silence_unless_frozen(rig):
    sim, conn, _ = rig
    sim.script.out_int[0] = STATUS_READY
    conn.status_sent = STATUS_READY
    assert not sim._silence_is_ours(), "a client told it may send, and silent, is silent"
    conn.status_sent = STATUS_DONE
    assert sim._silence_is_ours(), "the client waits for the ready this simulator owes it"
    sim.freeze()
    assert not sim._silence_is_ours(), "a frozen stream is a held-back network: it counts"
    sim.freeze(False)
    sim.script.out_int[0] = conn.status_sent  # a hung script: its state does not change
    assert not sim._silence_is_ours()


@pytest.mark.slow
def test_the_simulator_process_runs_every_thread_real_time_where_granted():
    """A controller never waits for the PC's CPU: where SCHED_FIFO is granted every thread of
    the simulator's process has it from its start (the cycle, the servers, the pipe), and
    numpy's pool, whose threads spin while they wait, is not there to hold a core."""
    with URSimProcess() as sim:
        policies = thread_policies(sim.pid)
        env = Path(f"/proc/{sim.pid}/environ").read_bytes().split(b"\0")
    want = os.SCHED_FIFO if fifo_granted() else os.SCHED_OTHER
    assert set(policies.values()) == {want}, policies
    assert b"OPENBLAS_NUM_THREADS=1" in env
