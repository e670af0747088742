"""``deepxpalm demo``'s palm fails safe: its operator node killed or frozen, the palm is lifted.

One demo as a user runs it (``--json``), with one grasp held for the whole
run so the palm is pressed whenever an operator node renders it. The
operator node and the servo bus simulator are the demo's children, found in
/proc as ``ps`` shows them; the palm is read from outside every process, on
the bus simulator's front panel (its ``--status-file``: the goals and every
goal write). ``kill -9`` of the operator: the demo's supervisor runs the
unit's ExecStopPost (``deepxpalm palm lift``) and the palm is off within the
product's 500 ms. SIGSTOP: the demo's watchdog (the unit's WatchdogSec)
ends the node and the palm is off within the window plus 500 ms. After
each, the demo goes on: a new operator node presses the palm again.
"""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import pytest
from tests_support import child_processes

from deploy.units.policy import policy
from deploy.units.readiness import NotReady
from deploy.units.service import Service
from harness.faults.probes import PalmProbe

# the palm is judged through the servo simulator's pseudo-terminal, within 500 ms of a death
pytestmark = [pytest.mark.slow, pytest.mark.pty, pytest.mark.timeout(300)]

#: the product's bound: a dead operator's palm is lifted within this
KILL_LIFT_S = 0.5
#: counts from the retract pose: a linkage on the palm
PALM_PRESSED = 50.0
OPERATOR = policy("operator")
#: one grasp, held for the whole run: the palm is pressed whenever a node renders it
_HELD_GRASP = (
    "robot.tactile.board.script={loop=false, start_delay_s=0.5, grasps=[{pattern=6, "
    "grip_level=25, ramp_s=0.1, hold_s=3600.0}]}"
)


class Demo:
    def __init__(self, tmp: Path) -> None:
        # --dashboard: the demo names its page once it is up (the robot heard): before that, an
        # operator's end is a failed start, which ends the demo
        argv = ["demo", "--json", "--no-video", "--dashboard"]
        argv += ["--set", "operator.dashboard.port=0"]  # a free one, kept across restarts
        argv += ["--duration", "600", "--set", "robot.render.mode=direct", "--set", _HELD_GRASP]
        self.stdout, self.stderr = tmp / "stdout", tmp / "stderr"
        self.service = Service("demo", argv, self.stderr, stdout=self.stdout)
        self.proc = self.service.start()
        self.started = time.monotonic()

    def wait_until_up(self, timeout_s: float = 120.0) -> None:
        """Until the demo said READY=1: every process of it up."""
        try:
            self.service.wait_ready(timeout_s)
        except NotReady as e:
            raise AssertionError(f"the demo never came up: {e}{self.tail()}") from None

    def child(self, role: str, timeout_s: float = 90.0, not_pid: int | None = None) -> int:
        """The pid of the demo's ``role`` child (a new one: not ``not_pid``)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            pid = child_processes(self.proc.pid).get(role)
            if pid is not None and pid != not_pid:
                return pid
            if self.proc.poll() is not None:
                break
            time.sleep(0.05)
        raise AssertionError(f"the demo has no {role} child{self.tail()}")

    def servo_panel(self) -> Path:
        """The bus simulator's front panel, from its command line as ``ps`` shows it."""
        with open(f"/proc/{self.child('servos')}/cmdline", "rb") as f:
            words = f.read().decode().split("\0")
        return Path(words[words.index("--status-file") + 1])

    def tail(self) -> str:
        err = self.stderr.read_text(errors="replace")
        return f"\nthe demo's stderr:\n{err[-3000:]}"

    def finish(self) -> tuple[int, dict]:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)  # Ctrl-C, as a user ends it
        self.proc.wait(timeout=90)
        out = self.stdout.read_text(errors="replace")
        return self.proc.returncode, json.loads(out[out.index("{") :])


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    from operator_side.palm.renderer import LinkGlideRenderer, RendererConfig
    from operator_side.servos.feetech import FeetechConfig

    retract = LinkGlideRenderer(RendererConfig(), FeetechConfig().calibration).retract_goals
    d = Demo(tmp_path_factory.mktemp("demo-palm"))
    palm = None
    try:
        # read from the bus's start (before any operator node: its first retract pose)
        palm = PalmProbe(d.servo_panel(), retract).start()
        d.wait_until_up()
        yield d, palm
    finally:
        if palm is not None:
            palm.close()
        d.service.stop(0)
        d.service.close()


def _pressed_by(d: Demo, palm: PalmProbe, pid: int, since: float, timeout_s: float = 90.0) -> None:
    """Until operator ``pid`` presses the palm: at the retract pose after ``since`` (the demo's
    start: the node writes it at its start, and the bus's power-up pose is not it; a fault: the
    lift wrote it, and only a new node presses after it), then the last 0.3 s all on the palm."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        up = next((s.t_s for s in palm.between(since) if s.value == 0), None)
        recent = palm.between(time.monotonic() - 0.3)
        if up is not None and recent and min(s.value for s in recent) > PALM_PRESSED:
            assert _alive(pid), f"operator {pid} ended{d.tail()}"
            return
        assert d.proc.poll() is None, f"the demo ended{d.tail()}"
        time.sleep(0.1)
    seen = palm.between(since)
    up = next((s.t_s - since for s in seen if s.value == 0), None)
    recent = [round(s.value) for s in palm.between(time.monotonic() - 0.3)]
    pytest.fail(
        f"operator {pid} never pressed the palm within {timeout_s:.0f} s: the probe read "
        f"{len(seen)} samples since, the first {seen[0].t_s - since if seen else None} s after "
        f"it, retract pose at {up} s, {len(palm.goal_writes)} goal writes in all, the last "
        f"0.3 s {recent}{d.tail()}"
    )


def _alive(pid: int) -> bool:
    """Running, not ended: a child not yet reaped is a zombie (state Z) in /proc."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except (FileNotFoundError, ProcessLookupError):  # reaped before the open, or during the read
        return False


def _lifted_after(palm: PalmProbe, t_fault: float, pid: int, within_s: float) -> tuple:
    """(seconds from the fault to the palm off, to the process's end); None: not seen in
    ``within_s`` plus 5 s."""
    ended = None
    deadline = t_fault + within_s + 5.0
    while time.monotonic() < deadline:
        if ended is None and not _alive(pid):
            ended = time.monotonic() - t_fault
        off = [s.t_s for s in palm.between(t_fault) if s.value == 0]
        if off and ended is not None:
            return off[0] - t_fault, ended
        time.sleep(0.01)
    off = [s.t_s for s in palm.between(t_fault) if s.value == 0]
    return (off[0] - t_fault if off else None), ended


def test_the_unit_policy_is_what_the_bounds_assume():
    assert OPERATOR is not None
    assert 0 < OPERATOR.watchdog_sec <= 2.0
    assert OPERATOR.stop_post[:2] == ("palm", "lift")


def test_a_killed_operator_lets_go_of_the_palm_and_the_demo_goes_on(demo):
    d, palm = demo
    pid = d.child("operator")
    _pressed_by(d, palm, pid, d.started)
    t_fault = time.monotonic()
    os.kill(pid, signal.SIGKILL)
    lifted, ended = _lifted_after(palm, t_fault, pid, KILL_LIFT_S)
    print(f"kill -9: process gone after {ended} s, palm lifted after {lifted} s")
    assert lifted is not None, f"the palm was never lifted after kill -9{d.tail()}"
    assert lifted <= KILL_LIFT_S, (
        f"kill -9: the palm was lifted {lifted:.3f} s after the fault, over the "
        f"{KILL_LIFT_S:g} s bound{d.tail()}"
    )
    _pressed_by(d, palm, d.child("operator", not_pid=pid), t_fault)  # restarted, feels again


def _watchdog_fired(d: Demo, pid: int) -> float | None:
    """Wall time of the demo's log line that says its watchdog ended ``pid`` (ms resolution)."""
    import datetime

    needle = f"watchdog: pid {pid} silent for"
    for line in d.stderr.read_text(errors="replace").splitlines():
        if needle in line:
            stamp = datetime.datetime.strptime(line[:23], "%Y-%m-%d %H:%M:%S,%f")
            return stamp.timestamp()  # logging's asctime is local time, as is a naive datetime
    return None


def test_a_frozen_operator_is_ended_by_the_demos_watchdog_and_lets_go(demo):
    d, palm = demo
    pid = d.child("operator")
    _pressed_by(d, palm, pid, d.started)
    # the watchdog is armed by the node's READY=1, sent within 0.5 s of its loop's first turn
    # (as systemd's: a node frozen before it is its start timeout's, not the watchdog's)
    time.sleep(1.0)
    t_fault_wall, t_fault = time.time(), time.monotonic()
    os.kill(pid, signal.SIGSTOP)
    window = OPERATOR.watchdog_sec
    lifted, ended = _lifted_after(palm, t_fault, pid, window + KILL_LIFT_S)
    fired = _watchdog_fired(d, pid)
    print(f"SIGSTOP: watchdog fired after {fired and fired - t_fault_wall} s, process ended")
    print(f"after {ended} s, palm lifted after {lifted} s")
    assert fired is not None, f"the demo's watchdog never ended the frozen operator{d.tail()}"
    # the watchdog counts from the node's last ping (every quarter window, before the fault),
    # and the demo's supervisor checks it every 20 ms: read off its own log line's time (this
    # test's polling of /proc, on a saturated machine, is no clock for it)
    assert fired - t_fault_wall <= window + 0.25, (
        f"the watchdog fired {fired - t_fault_wall:.2f} s after SIGSTOP{d.tail()}"
    )
    # then SIGABRT (with SIGCONT) ends the node, its stacks dumped, before the palm's bound
    assert ended is not None, f"the frozen operator (pid {pid}) was never ended{d.tail()}"
    assert ended <= window + KILL_LIFT_S, f"the node ended {ended:.2f} s after SIGSTOP{d.tail()}"
    assert lifted is not None, f"the palm was never lifted after SIGSTOP{d.tail()}"
    assert lifted <= window + KILL_LIFT_S, (
        f"SIGSTOP: the palm was lifted {lifted:.3f} s after the fault, over the watchdog's "
        f"{window:g} s + {KILL_LIFT_S:g} s{d.tail()}"
    )
    _pressed_by(d, palm, d.child("operator", not_pid=pid), t_fault)


def test_the_demo_reports_both_ends_and_no_error(demo):
    d, _ = demo
    code, summary = d.finish()
    operator = summary["processes"]["children"]["operator"]
    events = "\n".join(summary["processes"]["events"])
    assert code == 0 and summary["errors"] == [], summary["errors"]
    killed, aborted = operator["exit_codes"]
    assert killed == -signal.SIGKILL, operator
    if aborted == -signal.SIGSEGV:
        # the watchdog's SIGABRT comes with SIGCONT: faulthandler's dump of every thread runs
        # while the resumed main thread changes its frames, and may crash reading them (seen
        # once). The abort is what ended the node; its dump says so first
        log = Path(operator["log"]).read_text()
        assert "Fatal Python error: Aborted" in log.split("Segmentation fault")[0], log[-3000:]
    else:
        assert aborted == -signal.SIGABRT, operator
    assert operator["restarts"] == 2 and operator["state"] == "running", operator
    assert "ended by its watchdog" in events, events
    assert summary["stimuli_received"] > 0 and summary["servo_writes"] > 0
    lifts = Path(summary["logs"], "palm-lift.log").read_text()
    assert lifts.count("palm lifted") == 2, lifts
    runs = operator["stop_post"]
    print(f"deepxpalm palm lift, start to end: {[r['took_s'] for r in runs]} s")
    assert [r["exit_code"] for r in runs] == [0, 0], runs
