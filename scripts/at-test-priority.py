"""Run a command in a session of its own, above the machine's ordinary work.

    python scripts/at-test-priority.py NICE [--group GROUP_NICE] [--then-group GROUP_NICE]
                                       -- COMMAND [ARGS ...]

The test lanes run through this (the Makefile's ``TEST_NICE``). Their
deployments stand for robot PCs, controllers and boards of their own, which
a shared machine's other jobs (a CI machine's other builds, two busy loops)
do not share, and their budgets (the 400 ms stop, the 150 ms staleness) are
the product's. Inside a lane the nodes still run above the rest, at their
units' ``Nice=-10``.

A priority alone is not enough where the kernel groups processes by session
before it weighs their priorities (``sched_autogroup``, on by default on
most distributions): a busy loop started from the same shell would share
the lanes' group and take its share of it. So the command gets a session
(and so a group) of its own, at ``GROUP_NICE`` (``NICE`` if not given)
against the other sessions, while its processes run at ``NICE`` inside it:
the Makefile's group at -20 outweighs a session at nice 0 about 87 to 1,
and its processes at -5 leave the nodes and simulated hardware (at -10)
above the tests' own processes. The kernel's own workers get little too
(those that carry a pseudo-terminal's bytes run at nice 0 outside any
session): with the group saturated beside a test run, a pty's round trip
took up to 290 ms, on an otherwise quiet machine 10 to 12 ms
(``scripts/pty-latency-under-load.py``). Ctrl-C and a stop reach
it as before: this process forwards them to its process group.
Where the user may not raise a priority (not root, no CAP_SYS_NICE), the
command runs at the one it has, and one line says so.

``--then-group``: the weight the session's group takes when this process gets
SIGUSR1. The Makefile runs the lane of untimed tests beside the timed lanes
in a group that gets only what they leave, and gives it their weight once they
are done.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import time
from pathlib import Path

FORWARDED = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def _raise_priority(nice: int, group: int, then_group: int | None = None) -> str | None:
    """In the child, after setsid: the group's and the process's niceness; why not, if not.

    A group meant to weigh less than the lanes' (``then_group``, theirs) that may not be
    raised goes as far below a session at nice 0, where the lanes then run, as it was to be
    below theirs: the untimed lane still gives way to the timed ones.
    """
    try:
        _write_group(os.getpid(), group)
    except FileNotFoundError:
        pass  # no autogroup: the process's niceness is all there is
    except OSError as e:
        if then_group is None or group <= then_group:
            return f"the session's group: {e.strerror}"
        below = min(19, group - then_group)
        try:
            _write_group(os.getpid(), below)
        except OSError:
            return f"the session's group: {e.strerror}"
        return f"the session's group: {e.strerror}; at nice {below}, below the lanes' instead"
    try:
        os.nice(nice - os.nice(0))
    except OSError as e:
        return f"the process: {e.strerror}"
    return None


#: the kernel takes one group change every 100 ms from a user without CAP_SYS_ADMIN, counting
#: everyone's (EAGAIN meanwhile): a busy test run starts sessions, each with its group set
GROUP_RETRY_S = 0.11
GROUP_TRIES = 20


def _write_group(pid: int, group: int) -> None:
    """The scheduling group of ``pid``'s session at niceness ``group`` (``sched_autogroup``);
    a change the kernel puts off (EAGAIN: another was made in the last 100 ms) is tried again."""
    for attempt in range(GROUP_TRIES):
        try:
            Path(f"/proc/{pid}/autogroup").write_text(str(group))
            return
        except BlockingIOError:
            if attempt == GROUP_TRIES - 1:
                raise
            time.sleep(GROUP_RETRY_S)


def _set_group(pid: int, group: int) -> None:
    """``_write_group``, and nothing where there is no such group or it may not be set."""
    with contextlib.suppress(FileNotFoundError, ProcessLookupError, PermissionError):
        _write_group(pid, group)


def main(argv: list[str]) -> int:
    options: dict[str, str] = {}
    while len(argv) >= 3 and argv[1] in ("--group", "--then-group"):
        options[argv[1]], argv = argv[2], [argv[0], *argv[3:]]
    if len(argv) < 3 or argv[1] != "--":
        print(__doc__.strip().splitlines()[2].strip(), file=sys.stderr)
        return 2
    group = options.get("--group")
    then_group = options.get("--then-group")
    nice, command = int(argv[0]), argv[2:]
    group_nice = nice if group is None else int(group)
    pid = os.fork()
    if pid == 0:
        os.setsid()
        refused = _raise_priority(nice, group_nice, None if then_group is None else int(then_group))
        if refused is not None:
            print(
                f"at-test-priority: running at the priority it has, not nice {nice} "
                f"(group {group_nice}) ({refused})",
                file=sys.stderr,
            )
        try:
            os.execvp(command[0], command)
        except OSError as e:
            print(f"at-test-priority: cannot run {command[0]}: {e.strerror}", file=sys.stderr)
            os._exit(127)

    def forward(signum: int, _frame: object) -> None:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(pid, signum)

    for signum in FORWARDED:
        signal.signal(signum, forward)
    if then_group is not None:
        signal.signal(signal.SIGUSR1, lambda _s, _f: _set_group(pid, int(then_group)))
    _, status = os.waitpid(pid, 0)
    code = os.waitstatus_to_exitcode(status)
    return code if code >= 0 else 128 - code


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
