"""The demo's supervisor on real processes: a child that dies is started again after its
delay, one that keeps dying is given up on, and that ends the demo only if it is essential."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

import pytest

from deploy.units import process
from deploy.units.catalogue import UnitSpec
from deploy.units.child import START_LIMIT_BURST, Child, StopPost
from deploy.units.policy import RestartPolicy
from deploy.units.readiness import NotReady
from deploy.units.service import Service
from deploy.units.supervisor import Supervisor, _restart_s


@pytest.fixture(autouse=True)
def plain_commands(monkeypatch):
    """The children here are small programs, not ``deepxpalm``: spawned as they are, with
    everything else of a unit's (a session, its notify socket, dying with the test)."""
    monkeypatch.setattr(process, "cli_argv", lambda argv, _module: list(argv))


def _child(tmp_path, name: str, argv: list[str], delay: float, *args, **kw) -> Child:
    rules = kw.pop("rules", None)
    spec = UnitSpec(name, (), "a test's child", "nothing", rules=rules)
    return Child(Service(spec, argv, _log(tmp_path, name)), delay, *args, **kw)


def _python(code: str) -> list[str]:
    return [sys.executable, "-c", code]


# not a Python child: a stop that lands while an interpreter starts up exits 1, which
# the supervisor rightly reports (seen on a loaded machine); sleep(1) dies by SIGTERM whenever
SLEEPER = ["sleep", "60"]
FAILER = _python("raise SystemExit(3)")


def _log(tmp_path, name: str):
    path = tmp_path / f"{name}.log"
    path.touch()  # the supervisor quotes a child's log when it exits badly
    return path


def _poll_until(sup: Supervisor, errors: list, cond, timeout_s: float = 20.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, sup.summary()
        if not sup.poll(errors):
            return False
        time.sleep(0.02)
    return True


def test_the_delays_are_the_shipped_units():
    assert _restart_s("robot") == 3.0  # deploy/systemd/deepxpalm-robot.service
    assert _restart_s("video") == 0.2
    assert _restart_s("netsim") == 1.0  # no unit: the default


def test_a_killed_child_is_restarted_after_its_delay(tmp_path):
    sup, errors = Supervisor(), []
    child = sup.add(_child(tmp_path, "robot", SLEEPER, 0.3), ready=False)
    sup.armed = True
    first = child.proc.pid
    child.proc.kill()
    child.proc.wait()
    t0 = time.monotonic()
    _poll_until(sup, errors, lambda: child.proc.pid != first)
    assert time.monotonic() - t0 >= 0.3
    assert child.describe()["exit_codes"] == [-9] and child.describe()["restarts"] == 1
    assert "restarting in 0.3 s" in sup.events[0] and "restarted" in sup.events[1]
    assert "robot running (1 restart)" in sup.status_line()
    sup.stop_all(errors)
    assert errors == []


def test_a_child_that_keeps_dying_is_given_up_on(tmp_path):
    sup, errors = Supervisor(), []
    video = sup.add(_child(tmp_path, "video", FAILER, 0.01, False), ready=False)
    robot = sup.add(_child(tmp_path, "robot", SLEEPER, 0.01), ready=False)
    sup.armed = True
    _poll_until(sup, errors, lambda: video.gave_up)
    assert len(video.restart_times) == START_LIMIT_BURST and video.exits == [3] * 6
    assert sup.poll(errors)  # not essential: the demo runs on
    robot.essential = True
    robot.proc.kill()
    robot.restart_times = [time.monotonic()] * START_LIMIT_BURST  # as if it had looped
    robot.proc.wait()
    assert not _poll_until(sup, errors, lambda: False)  # essential: the demo must end
    assert robot.gave_up and "given up on" in sup.events[-1]
    sup.stop_all(errors)
    assert any("video was given up on" in e for e in errors), errors


#: a process that says when it starts, when SIGTERM reaches it and when it ends (0.3 s later)
SLOW_TO_STOP = """#!/bin/sh
say() { echo "$1 $(date +%s.%N)" >> "$0.times"; }
trap 'say term; sleep 0.3; say end; exit 0' TERM
say up
while :; do sleep 0.02; done
"""


def test_the_nodes_stop_together_and_what_outlives_them_after(tmp_path):
    """As systemd stops units with no ordering between them: the nodes' processes at once
    (one after another, a cell's three fabric clients took 4 s), then the router, the link
    and the simulated hardware they were talking to. Read from the processes' own clocks."""
    sup, errors = Supervisor(), []
    names = {"robot": False, "operator": False, "router": True, "sim-ur": True}
    for name, outlives in names.items():
        script = tmp_path / name
        script.write_text(SLOW_TO_STOP)
        script.chmod(0o755)
        spec = UnitSpec(name, (), "a test's child", "nothing", outlives_the_nodes=outlives)
        sup.add(Child(Service(spec, [str(script)], _log(tmp_path, name)), 0.01), ready=False)
    times = lambda n: dict(  # noqa: E731
        line.split() for line in (tmp_path / f"{n}.times").read_text().splitlines()
    )
    deadline = time.monotonic() + 10
    while not all((tmp_path / f"{n}.times").exists() for n in names):
        assert time.monotonic() < deadline, "the children never started"
        time.sleep(0.02)
    sup.stop_all(errors)
    assert errors == []
    t = {n: {k: float(v) for k, v in times(n).items()} for n in names}
    nodes = [n for n, outlives in names.items() if not outlives]
    rest = [n for n, outlives in names.items() if outlives]
    # together: each node was told to stop before any of them had ended
    assert max(t[n]["term"] for n in nodes) < min(t[n]["end"] for n in nodes), t
    assert max(t[n]["term"] for n in rest) < min(t[n]["end"] for n in rest), t
    # and what outlives the nodes only once every node had ended
    assert min(t[n]["term"] for n in rest) >= max(t[n]["end"] for n in nodes), t


def test_a_child_failing_while_the_demo_starts_ends_it(tmp_path):
    sup, errors = Supervisor(), []
    child = _child(tmp_path, "robot", _python("raise SystemExit(2)"), 0.01)
    sup.add(child, ready=False).proc.wait()
    assert not sup.poll(errors)  # not armed: a wrong setting would otherwise loop
    assert "robot stopped early with 2" in errors[0]


def test_a_child_that_ends_before_it_is_ready_fails_its_start_with_its_log(tmp_path):
    sup = Supervisor()
    code = "import sys; print('no such device', file=sys.stderr); raise SystemExit(2)"
    with pytest.raises(NotReady, match=r"robot .* ended with 2 before it was ready: no such"):
        sup.add(_child(tmp_path, "robot", _python(code), 0.01))
    sup.stop_all([])


#: a unit's process as common.process.sd_notify makes it: READY=1, then WATCHDOG=1 every 50 ms
PINGER = """
import time
from common.process.sd_notify import Notifier
n = Notifier()
n.ready()
while True:
    n.watchdog()
    time.sleep(0.05)
"""


#: the frozen child's WatchdogSec=
WINDOW_S = 1.0


def test_a_frozen_child_is_ended_by_its_watchdog_then_its_stop_post_runs(tmp_path):
    """SIGSTOP: silent for the watchdog's window, it is sent SIGABRT and SIGCONT (as systemd
    does), its ExecStopPost runs before the restart, and the new process is watched again."""
    marks = tmp_path / "stop-post"
    post = StopPost(
        "op",
        lambda: subprocess.Popen(["sh", "-c", f"echo ran >> {marks}"]),
    )
    # a window a busy machine's 50 ms pinger keeps (0.3 s: its restarted process, starved for
    # longer beside the suite's deployments and two busy loops, was rightly ended as well)
    rules = RestartPolicy("op", "on-failure", 0.1, watchdog_sec=WINDOW_S, timeout_abort_sec=1.0)
    sup, errors = Supervisor(), []
    child = sup.add(_child(tmp_path, "op", _python(PINGER), 0.1, stop_post=post, rules=rules))
    watchdog = child.watchdog
    assert watchdog is not None
    sup.armed = True
    first = child.proc.pid
    _poll_until(sup, errors, lambda: watchdog.pings >= 3)
    child.proc.send_signal(signal.SIGSTOP)
    t0 = time.monotonic()
    _poll_until(sup, errors, lambda: child.proc.pid != first)
    fired = [t - t0 for t, pid in watchdog.fired if pid == first]
    assert fired and WINDOW_S - 0.1 <= fired[0] <= WINDOW_S + 0.5, f"fired at {fired} s"
    assert child.exits == [-6], child.exits  # SIGABRT
    assert marks.read_text() == "ran\n" and post.runs[0][1] <= child.started_at
    assert "ended by its watchdog" in sup.events[0], sup.events
    pings = watchdog.pings
    _poll_until(sup, errors, lambda: watchdog.pings >= pings + 3)  # the new one, watched
    assert len(watchdog.fired) == 1
    sup.stop_all(errors)
    assert errors == []


def test_a_stopped_child_is_stopped_at_the_end_without_waiting(tmp_path):
    """SIGTERM with SIGCONT, as systemd stops a unit: a stopped process ends at once."""
    sup, errors = Supervisor(), []
    child = sup.add(_child(tmp_path, "robot", SLEEPER, 0.3), ready=False)
    child.proc.send_signal(signal.SIGSTOP)
    t0 = time.monotonic()
    sup.stop_all(errors)
    assert time.monotonic() - t0 < 5.0 and errors == [], errors


def test_a_child_that_ended_while_its_stop_post_runs_is_no_error_when_the_demo_stops(tmp_path):
    """Ctrl-C just after a child ended (a watchdog's kill), its ExecStopPost (the palm's lift)
    still running: the lift runs to its end, the exit is counted and said, and it is not
    reported as an error (it was reported as "exited with -6" before)."""
    marks = tmp_path / "stop-post"
    post = StopPost("op", lambda: subprocess.Popen(["sh", "-c", f"sleep 0.5; echo ran >> {marks}"]))
    sup, errors = Supervisor(), []
    child = sup.add(_child(tmp_path, "op", SLEEPER, 0.1, stop_post=post), ready=False)
    sup.armed = True
    child.proc.send_signal(signal.SIGABRT)
    child.proc.wait()
    assert sup.poll(errors)  # the lift starts; the end waits for it
    assert post.runs == [] and child.exits == []
    sup.stop_all(errors)
    assert errors == [], errors
    assert marks.read_text() == "ran\n" and [r[2] for r in post.runs] == [0]
    assert child.exits == [-signal.SIGABRT] and "as the demo stopped" in sup.events[-1]
