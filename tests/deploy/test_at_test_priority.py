"""The launcher the Makefile runs the test lanes through: a session of its own, a priority,
the command's exit status and Ctrl-C passed through."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "at-test-priority.py"
REPORT = "import os; print(os.getsid(0), os.nice(0))"
GROUP = Path("/proc/self/autogroup")  # absent on a kernel without sched_autogroup
GROUP_REPORT = (
    "import os, pathlib; g = pathlib.Path('/proc/self/autogroup');"
    "print(os.nice(0), g.read_text().split()[-1] if g.exists() else 'none')"
)


def _run(*command: str, nice: int = -5, group: int | None = None) -> subprocess.CompletedProcess:
    options = [] if group is None else ["--group", str(group)]
    return subprocess.run(
        [sys.executable, str(SCRIPT), str(nice), *options, "--", *command],
        capture_output=True,
        text=True,
        timeout=30,
    )


def test_the_command_runs_in_a_session_of_its_own_at_the_priority_or_says_why_not():
    done = _run(sys.executable, "-c", REPORT)
    assert done.returncode == 0, done.stderr
    session, nice = map(int, done.stdout.split())
    assert session != os.getsid(0)
    if nice == -5:
        assert "running at the priority it has" not in done.stderr
    else:  # not permitted here: the same command at the priority it had, and one line
        assert nice == os.nice(0) and "running at the priority it has" in done.stderr


def test_the_sessions_group_may_weigh_more_than_the_processes_inside_it():
    done = _run(sys.executable, "-c", GROUP_REPORT, nice=-5, group=-10)
    assert done.returncode == 0, done.stderr
    nice, group = done.stdout.split()
    if "running at the priority it has" in done.stderr:  # not permitted here
        assert int(nice) == os.nice(0)
    else:
        assert int(nice) == -5 and group == ("-10" if GROUP.exists() else "none")


def test_the_exit_status_and_a_death_by_signal_come_back_as_a_shell_reports_them():
    assert _run(sys.executable, "-c", "raise SystemExit(5)").returncode == 5
    assert _run("sh", "-c", "kill -9 $$").returncode == 128 + signal.SIGKILL
    missing = _run("/nonexistent/command")
    assert missing.returncode == 127 and "cannot run /nonexistent/command" in missing.stderr


def test_a_stop_reaches_the_command():
    proc = subprocess.Popen(
        [sys.executable, str(SCRIPT), "-5", "--", "sleep", "30"], stderr=subprocess.PIPE
    )
    time.sleep(0.5)
    t0 = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=10) == 128 + signal.SIGTERM
    assert time.monotonic() - t0 < 5


def test_sigusr1_gives_the_session_the_group_weight_it_is_to_take_then():
    report = f"{sys.executable} -c \"import pathlib; print(pathlib.Path('{GROUP}').read_text())\""
    options = ["--group", "-10", "--then-group", "-20", "--"]
    proc = subprocess.Popen(
        [sys.executable, str(SCRIPT), "-5", *options, "sh", "-c", f"{report}; read _; {report}"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        before = proc.stdout.readline().split()[-1:]
        proc.send_signal(signal.SIGUSR1)
        time.sleep(0.2)  # the launcher's handler runs between its waits
        after, errors = proc.communicate("\n", timeout=10)
    finally:
        proc.kill()
    assert proc.returncode == 0, errors
    if not GROUP.exists() or "running at the priority it has" in errors:
        return  # no autogroup here, or not permitted: nothing to weigh
    assert (before, after.split()[-1:]) == (["-10"], ["-20"])


def test_a_lighter_group_that_may_not_be_raised_stays_as_far_below_the_lanes():
    """Without the privilege to raise a group (a developer's own account), the timed lanes run
    in sessions at nice 0: a lighter group asked at -10 goes to +10, as far below them as -10
    is below -20, rather than weighing as much as they do."""
    unprivileged = ["setpriv", "--reuid=nobody", "--regid=nogroup", "--clear-groups"]
    launcher = [sys.executable, str(SCRIPT), "-5", "--group", "-10", "--then-group", "-20", "--"]
    done = subprocess.run(
        [*(unprivileged if os.geteuid() == 0 else []), *launcher, "cat", str(GROUP)],
        capture_output=True,
        text=True,
        timeout=30,
    )
    if GROUP.exists():  # else nothing to weigh (and nothing to read)
        assert done.returncode == 0, done.stderr
        assert done.stdout.split()[-1:] == ["10"], done.stdout
        assert "below the lanes' instead" in done.stderr, done.stderr
