"""Priorities: a child at its unit's Nice= (keeping its parent's group weight when it leads a
session of its own), a simulator's thread at the hardware's."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from common.devices.lifecycle import SIMULATED_HARDWARE_NICE, as_hardware, at_niceness
from deploy.units.policy import set_niceness, unit_nice

GROUP = Path("/proc/self/autogroup")  # absent on a kernel without sched_autogroup
REPORT = (
    "import os, pathlib; g = pathlib.Path('/proc/self/autogroup');"
    "print(os.nice(0), g.read_text().split()[-1] if g.exists() else 'none')"
)


def _child(nice: int, new_session: bool) -> tuple[int, str]:
    out = subprocess.run(
        [sys.executable, "-c", REPORT],
        capture_output=True,
        text=True,
        timeout=30,
        start_new_session=new_session,
        preexec_fn=lambda: set_niceness(nice),
    )
    process, group = out.stdout.split()
    return int(process), group


def test_a_session_leader_keeps_its_parents_group_weight_and_gets_its_units_niceness():
    mine = GROUP.read_text().split()[-1] if GROUP.exists() else "none"
    process, group = _child(-3, new_session=True)
    assert group == mine  # not the new session's default 0
    if os.geteuid() == 0:
        assert process == -3
    else:  # not permitted to raise it: the same program at the priority it had
        assert process == os.nice(0)


def test_a_child_in_its_parents_session_leaves_the_sessions_group_alone():
    mine = GROUP.read_text().split()[-1] if GROUP.exists() else "none"
    process, group = _child(os.nice(0) + 1, new_session=False)  # lowering needs no privilege
    assert process == os.nice(0) + 1
    assert group == mine


def test_a_simulators_thread_runs_at_the_hardware_priority_and_its_process_does_not():
    mine = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    seen: dict[str, int] = {}

    def serve() -> None:
        seen["simulator"] = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
        child = threading.Thread(target=lambda: seen.update(connection=os.nice(0)))
        child.start()  # a connection's thread, started by the simulator's
        child.join()

    thread = threading.Thread(target=as_hardware(serve))
    thread.start()
    thread.join()
    expected = SIMULATED_HARDWARE_NICE if os.geteuid() == 0 else mine
    assert seen == {"simulator": expected, "connection": expected}
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == mine


def test_a_thread_already_above_the_asked_priority_keeps_its_own():
    seen: dict[str, int] = {}

    def higher() -> None:  # a node started at -15, say
        tid = threading.get_native_id()
        try:
            os.setpriority(os.PRIO_PROCESS, tid, -15)
        except OSError:  # not permitted here: nothing to keep
            return
        inner = threading.Thread(target=at_niceness(-10, lambda: seen.update(inner=os.nice(0))))
        inner.start()
        inner.join()

    thread = threading.Thread(target=higher)
    thread.start()
    thread.join()
    assert seen == ({"inner": -15} if os.geteuid() == 0 else {})


def test_a_target_run_in_place_gives_the_caller_its_priority_back():
    """A target run in place, not on a thread of its own: the caller goes on at the priority
    it had."""
    tid = threading.get_native_id()
    mine = os.getpriority(os.PRIO_PROCESS, tid)
    during = as_hardware(lambda: os.getpriority(os.PRIO_PROCESS, threading.get_native_id()))()
    assert during == (min(SIMULATED_HARDWARE_NICE, mine) if os.geteuid() == 0 else mine)
    assert os.getpriority(os.PRIO_PROCESS, tid) == mine


def _tasks(pid: int) -> list[int]:
    return [int(t) for t in os.listdir(f"/proc/{pid}/task")]


@pytest.mark.slow
@pytest.mark.untimed
def test_a_robot_nodes_arm_process_runs_real_time_and_the_node_at_its_units_nice(tmp_path):
    """Read from the running processes' ``/proc``: the robot node's threads at the unit's
    Nice=-10 (the UR driver is not in it), its arm process's at SCHED_FIFO: the keep-alive
    and the deadman at ``realtime_priority``, every other thread one step below but one:
    ur-rtde's polling loops, in the fair scheduler at the unit's niceness with their timer
    slacks (the pose read back; the control interface's loop real-time during a call only)."""
    from harness.bench.command_path import RobotUnderCommands
    from harness.processes import children_of, cmdline
    from robot_side.arm.ur_rtde import URArmConfig
    from robot_side.arm.ur_rtde.connection import RECEIVE_THREAD_SLACK_NS
    from robot_side.arm.ur_rtde.control_receiver import CONTROL_THREAD_SLACK_NS

    with RobotUnderCommands(tmp_path) as rig:
        pid = rig.proc.pid
        nice = {tid: os.getpriority(os.PRIO_PROCESS, tid) for tid in _tasks(pid)}
        (arm,) = [c for c in children_of(pid) if "robot_side.arm.process" in (cmdline(c) or [])]
        # right after a command the keep-alive makes its next call in the fair scheduler, a
        # few ms until the controller's stream has moved past it (ControlLine._unspun): read
        # again until the deadman and the keep-alive both show at the top, 2 s at most
        deadline = time.monotonic() + 2.0
        while True:
            policy = {
                tid: (os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority)
                for tid in _tasks(arm)
            }
            at_top = list(policy.values()).count((os.SCHED_FIFO, URArmConfig().realtime_priority))
            if at_top >= 2 or os.geteuid() != 0 or time.monotonic() > deadline:
                break
            time.sleep(0.01)
        fair = {
            tid: (os.getpriority(os.PRIO_PROCESS, tid), _timer_slack_ns(tid))
            for tid, (p, _) in policy.items()
            if p == os.SCHED_OTHER
        }
        names = {tid: _comm(tid) for tid in policy}
    if os.geteuid() != 0:  # no right to raise: every thread keeps what it was started with
        assert all(p == os.SCHED_OTHER for p, _ in policy.values()), policy
        return
    assert set(nice.values()) == {unit_nice("robot")}, nice
    top = URArmConfig().realtime_priority
    real_time = {t: p for t, p in policy.items() if t not in fair}
    assert set(real_time.values()) <= {(os.SCHED_FIFO, top), (os.SCHED_FIFO, top - 1)}, policy
    assert list(policy.values()).count((os.SCHED_FIFO, top)) >= 2, f"deadman, keep-alive: {policy}"
    # ur-rtde's two polling loops in the fair scheduler with their timer slacks: the receive
    # interface's always, the control interface's between calls (one step under the top
    # while a call waits on it)
    assert {names[t] for t in fair} <= {"rtde-receive", "rtde-control"}, (names, policy)
    receive = [fair[t] for t in fair if names[t] == "rtde-receive"]
    assert receive == [(unit_nice("robot"), RECEIVE_THREAD_SLACK_NS)], (fair, policy)
    control = [t for t in policy if names[t] == "rtde-control"]
    assert control, names
    for t in control:
        between = fair.get(t) == (unit_nice("robot"), CONTROL_THREAD_SLACK_NS)
        assert between or policy[t] == (os.SCHED_FIFO, top - 1), (fair, policy)


def _comm(tid: int) -> str:
    try:
        return Path(f"/proc/{tid}/comm").read_text().strip()
    except OSError:  # it ended meanwhile
        return ""


def _timer_slack_ns(tid: int) -> int:
    return int(Path(f"/proc/{tid}/timerslack_ns").read_text())
