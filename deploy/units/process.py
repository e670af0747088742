"""Starting and stopping one process, as systemd does it for a unit.

:func:`spawn` runs ``deepxpalm ARGS`` (``python -m deploy.cli`` with this
interpreter, so a checkout put first on ``PYTHONPATH`` runs its own code) in
a session of its own (Ctrl-C reaches the parent alone, which stops its
children in order), at the niceness its unit's ``Nice=`` gives it, and with
``PR_SET_PDEATHSIG`` so that it dies with its parent, even one ended by
SIGKILL. :func:`stop` is ``systemctl stop``: a signal (SIGTERM, then SIGCONT
so that a stopped process runs its handler), a wait of ``TimeoutStopSec=``,
then SIGKILL.

Every process the demo, the fault matrix, the fleet, the soak and the bench
start is started and stopped here (``tests/deploy/test_one_process_model.py``
finds any second copy).
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import IO, Any

from deploy.units.policy import set_niceness, unit_nice

#: systemd's default ``TimeoutStopSec=``-like wait of the demo and the harness: a node
#: writes its statistics and recording, the video server closes its viewers, within it
STOP_TIMEOUT_S = 10.0

#: a process ended by one of these stopped as asked (systemd counts them clean too)
CLEAN_ENDS = frozenset({0, -signal.SIGINT, 130, -signal.SIGTERM, 143})


#: the module a child runs: the ``deepxpalm`` command
CLI = "deploy.cli"


def cli_argv(args: list[str], module: str = CLI) -> list[str]:
    """The command line of ``deepxpalm ARGS`` (or ``python -m MODULE ARGS``) run by this
    interpreter."""
    return [sys.executable, "-m", module, *args]


def die_with_parent() -> None:
    """In the child: SIGTERM when the parent dies, even by SIGKILL (Linux), so nothing lingers.

    The signal follows the *thread* that forked the child: a process started from a thread
    that ends before it is sent SIGTERM then. Start long-lived children from a thread that
    lives as long as they should (the main thread, or a supervisor's own).
    """
    with contextlib.suppress(OSError, AttributeError):
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


def spawn(
    unit: str | None,
    argv: list[str],
    log: Path | IO[Any] | int | None,
    env: Mapping[str, str] | None = None,
    stdin: IO[Any] | int | None = subprocess.DEVNULL,
    *,
    stdout: Path | IO[Any] | int | None = None,
    module: str = CLI,
    **popen: Any,
) -> subprocess.Popen:
    """``deepxpalm ARGV`` as a child: at the niceness of ``unit``'s ``Nice=``, dying with us.
    (``module``: another program of this interpreter's, ``python -m MODULE ARGV``: the
    bench's peers.)

    ``log``: where its output goes (a path is appended to: a restarted process's log
    follows the one before); stdout goes there too unless ``stdout`` says otherwise.
    ``env``: its whole environment (None: ours). ``stdin``: nothing by default (a pipe
    for commands). Other keywords go to :class:`subprocess.Popen` (``text=True``,
    ``start_new_session=False`` for a child that stays in our session).
    """
    nice = unit_nice(unit)

    def in_child() -> None:
        die_with_parent()
        set_niceness(nice)

    opened: list[IO[Any]] = []

    def target(where: Path | IO[Any] | int | None) -> IO[Any] | int | None:
        if isinstance(where, Path):
            opened.append(where.open("ab"))
            return opened[-1]
        return where

    if stdout is None:  # one stream: stderr joins stdout where the log goes
        out, err = target(log), (None if log is None else subprocess.STDOUT)
    else:
        out, err = target(stdout), target(log)
    popen.setdefault("start_new_session", True)
    try:
        return subprocess.Popen(
            cli_argv(argv, module),
            stdin=stdin,
            stdout=out,
            stderr=err,
            env=None if env is None else dict(env),
            preexec_fn=in_child,
            **popen,
        )
    finally:
        for f in opened:  # the child holds its own copy
            f.close()


def stop(
    popen: subprocess.Popen | None,
    timeout_s: float = STOP_TIMEOUT_S,
    sig: int = signal.SIGTERM,
    *,
    group: bool = False,
) -> bool:
    """``sig`` and SIGCONT, a wait of ``timeout_s``, then SIGKILL; True if it had to kill.

    SIGTERM by default, as ``systemctl stop`` sends it; not SIGINT, which a child of a
    shell without job control inherits ignored. ``group``: the child's whole process
    group (a child started in a session of its own, and its own children, as a browser's).
    A child that has already ended is reaped and left alone; ``timeout_s=0`` kills at once.
    """
    if popen is None or popen.poll() is not None:
        return False

    def send(s: int) -> None:
        with contextlib.suppress(ProcessLookupError):
            if group:
                os.killpg(popen.pid, s)
            else:
                popen.send_signal(s)

    if timeout_s > 0:
        send(sig)
        send(signal.SIGCONT)  # a stopped process runs, and so ends
        try:
            popen.wait(timeout=timeout_s)
            return False
        except subprocess.TimeoutExpired:
            pass
    send(signal.SIGKILL)
    popen.wait()
    return True
