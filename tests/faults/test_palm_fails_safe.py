"""The palm fails safe: a killed or frozen operator node leaves no linkage pressing the palm.

One deployment (``harness.faults.deployment``: every node and device a process
of its own, the operator under its unit's rules: its palm guard lifts the palm
as it ends, ExecStopPost= runs ``deepxpalm palm lift``, WatchdogSec= ends a
frozen node). The palm is read from outside
every node, from the servo simulator's front panel (its goals, and every goal
write in its log): pressed by the grasp, then lifted after the fault.
"""

from __future__ import annotations

import math
import signal
import time

import pytest

from deploy.units.policy import policy
from harness.faults.deployment import Deployment
from harness.faults.matrix import GRASP_LEVEL, PALM_PRESSED
from harness.faults.probes import PalmProbe
from operator_side.node import LIFT_ARRIVAL_S
from operator_side.servos.base import ARRIVED_COUNTS

#: the issue's bound: a killed operator's palm is lifted within this
KILL_LIFT_S = 0.5
#: what the palm guard prints once it lifted the palm
GUARD_LIFTED = "palm guard: the node ended, palm lifted"
OPERATOR = policy("operator")

# the palm is judged through the servo simulator's pseudo-terminal, within 500 ms of a death
pytestmark = pytest.mark.pty


@pytest.fixture(scope="module")
def deployment():
    from operator_side.palm.renderer import LinkGlideRenderer, RendererConfig
    from operator_side.servos.feetech import FeetechConfig

    retract = LinkGlideRenderer(RendererConfig(), FeetechConfig().calibration).retract_goals
    with Deployment() as d:
        palm = PalmProbe(d.servo_status, retract).start()
        try:
            yield d, palm
        finally:
            palm.close()


def _pressed(d: Deployment, palm: PalmProbe, timeout_s: float = 90.0) -> None:
    """Grasp until the palm feels it: pressed after the running node's own retract pose (the
    bus's power-up pose is neither), so the node is up and renders the grasp."""
    unit = d.units["operator"]
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        start = unit.started_at
        if not unit.alive():
            time.sleep(0.1)  # ended: its ExecStopPost, then the restart, are due
            continue
        d.operator_send({"action": "gripper_close", "grip_level": GRASP_LEVEL})
        since = palm.between(start)
        up = next((s.t_s for s in since if s.value == 0), None)
        recent = palm.between(time.monotonic() - 0.3)
        if up is not None and recent and min(s.value for s in recent) > PALM_PRESSED:
            return
        time.sleep(0.3)
    pytest.fail(f"the palm never felt the grasp within {timeout_s:.0f} s\n{d.log_tails()}")


def _lifted_after(d: Deployment, palm: PalmProbe, t_fault: float) -> tuple[float | None, list]:
    """Seconds from the fault to the palm's lift (None: never), once the unit's ExecStopPost
    ended (at most 60 s), and that run's (start, end, exit code) from the fault."""
    unit = d.units["operator"]
    deadline = time.monotonic() + 60.0
    while not [p for p in unit.stop_posts if p[0] >= t_fault] and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.2)  # the front panel's next rewrite
    post = [(round(a - t_fault, 3), round(b - t_fault, 3), c) for a, b, c in unit.stop_posts]
    off = [s.t_s for s in palm.between(t_fault) if s.value == 0]
    return (None if not off else off[0] - t_fault), [p for p in post if p[0] >= 0]


def _within(lifted: float, bound: float, what: str, post: list) -> None:
    assert lifted <= bound, (
        f"{what}: the palm was lifted {lifted:.3f} s after the fault, over the {bound:g} s "
        f"bound; ExecStopPost (start, end, exit) from the fault: {post}"
    )


def test_the_unit_policy_is_what_the_bounds_assume():
    assert OPERATOR is not None
    assert 0 < OPERATOR.watchdog_sec <= 2.0
    assert OPERATOR.stop_post[:2] == ("palm", "lift")


@pytest.mark.slow
def test_a_killed_operator_lets_go_of_the_palm(deployment):
    d, palm = deployment
    _pressed(d, palm)
    t_fault = time.monotonic()
    d.signal("operator", signal.SIGKILL)
    lifted, post = _lifted_after(d, palm, t_fault)
    assert post and post[0][2] == 0, f"deepxpalm palm lift failed: {post}\n{d.log_tails()}"
    assert lifted is not None and lifted <= post[0][1] + 0.2, (
        f"the palm was not lifted by the end of ExecStopPost: lifted at {lifted} s, "
        f"ExecStopPost {post}\n{d.log_tails()}"
    )
    _within(lifted, KILL_LIFT_S, "kill -9", post)
    # the node's palm guard lifted it (the ExecStopPost waited for the bus meanwhile)
    assert GUARD_LIFTED in d.units["operator"].handle.log_text(), d.log_tails()


@pytest.mark.slow
def test_a_frozen_operator_is_ended_by_its_watchdog_and_lets_go(deployment):
    d, palm = deployment
    _pressed(d, palm)
    unit = d.units["operator"]
    # its watchdog is armed by READY=1, which may come after the palm is pressed (a node
    # restarted by the test before this one): freeze it only once it is watched
    deadline = time.monotonic() + 10.0
    while not unit.watchdog.armed:
        assert time.monotonic() < deadline, f"the operator never said READY=1\n{d.log_tails()}"
        time.sleep(0.02)
    pid = unit.pid
    t_fault = time.monotonic()
    d.signal("operator", signal.SIGSTOP)
    lifted, post = _lifted_after(d, palm, t_fault)
    fired = [t - t_fault for t, p in unit.watchdog.fired if p == pid]
    assert fired, f"the watchdog never ended the frozen node (pid {pid})\n{d.log_tails()}"
    assert fired[0] <= OPERATOR.watchdog_sec + 0.5, f"the watchdog fired {fired[0]:.2f} s late"
    assert post and post[0][2] == 0, f"deepxpalm palm lift failed: {post}\n{d.log_tails()}"
    assert lifted is not None and lifted <= post[0][1] + 0.2, (
        f"the palm was not lifted by the end of ExecStopPost: lifted at {lifted} s, "
        f"ExecStopPost {post}\n{d.log_tails()}"
    )
    _within(lifted, OPERATOR.watchdog_sec + KILL_LIFT_S, "SIGSTOP", post)


@pytest.mark.slow
def test_a_stopped_operator_lets_go_of_the_palm_only_once_it_is_lifted(deployment):
    """``systemctl restart``: the node lifts the palm itself on its way out and keeps torque on
    until the linkages are there; each servo's torque off is read from the bus (where it was
    let go) before the unit's ExecStopPost opens the bus again.

    The ExecStopPost's first bytes on the bus are its retract goals: the node's torque off
    is what the bus took before them (on a loaded machine the pseudo-terminal may hand the
    node's last bytes to the bus after the node ended, even after the ExecStopPost began)."""
    d, palm = deployment
    _pressed(d, palm)
    unit = d.units["operator"]
    posts = len(unit.stop_posts)
    t_fault = time.monotonic()
    d.clean_restart("operator")
    post_start = unit.stop_posts[posts][0]
    deadline = time.monotonic() + 10.0  # its goals reach the front panel's log
    while palm.first_write_after(post_start) == math.inf and time.monotonic() < deadline:
        time.sleep(0.05)
    lift_opens = palm.first_write_after(post_start)
    offs = [(round(t - t_fault, 3), i) for t, i, _ in palm.releases if t >= t_fault]
    released: dict[int, int] = {}  # each servo's first torque off: the node's own
    for t, i, p in palm.releases:
        if t_fault <= t < lift_opens:
            released.setdefault(i, p)
    assert sorted(released) == [1, 2, 3, 4, 5, 6], (
        f"the node did not turn every servo's torque off on its way out: {released} (torque "
        f"offs from the stop: {offs}; "
        f"ExecStopPost began at {post_start - t_fault:.3f} s, its first write on the bus at "
        f"{lift_opens - t_fault:.3f} s)\n{d.log_tails()}"
    )
    away = {
        i: (p, palm.retract[i - 1])
        for i, p in released.items()
        if abs(p - palm.retract[i - 1]) > ARRIVED_COUNTS
    }
    assert not away, (
        f"servos let go before the retract pose (present, retract): {away}; the node waits "
        f"{LIFT_ARRIVAL_S:g} s for it\n{d.log_tails()}"
    )


@pytest.mark.slow
def test_a_briefly_stopped_operator_reports_how_late_its_loop_woke(deployment):
    """Held for less than its watchdog: the node runs on, and its status file (the interface
    the fault matrix reads, not a log line) counts the late wake-up and how late it was."""
    d, palm = deployment
    _pressed(d, palm)
    before = len(d.operator_late_wakes())
    pid = d.units["operator"].pid
    t_stop = time.monotonic()
    d.signal("operator", signal.SIGSTOP)
    time.sleep(0.6)
    t_cont = time.monotonic()  # before the signal: the node may run and write before we read
    d.signal("operator", signal.SIGCONT)
    deadline = t_cont + 5.0
    while len(d.operator_late_wakes()) == before and time.monotonic() < deadline:
        time.sleep(0.05)
    wakes = [(due - t_stop, woke - t_stop) for due, woke in d.operator_late_wakes()[before:]]
    assert wakes, f"no late wake-up reported after a 0.6 s stop\n{d.log_tails()}"
    assert any(woke >= t_cont - t_stop and woke - due >= 0.5 for due, woke in wakes), (
        f"(due, woke) from the stop: {wakes}; continued at {t_cont - t_stop:.3f} s"
    )
    assert d.units["operator"].pid == pid, "a node stopped for less than its WatchdogSec ended"
