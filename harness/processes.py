"""The harness's process toolkit: start ``deepxpalm`` as a child, stop a child, read /proc.

Every harness module that starts the product's command, stops a process or
reads a process's CPU time does it here, once:

- :func:`cli_argv` / :func:`spawn_cli`: ``python -m deploy.cli ARGS`` with this
  interpreter (a checkout put first on PYTHONPATH runs its own code), at the
  priority the systemd unit gives the role when one is named.
- :func:`stop`: a signal (SIGTERM, as ``systemctl stop`` sends), a wait, then
  SIGKILL, as systemd's ``TimeoutStopSec=`` does; says whether it had to kill.
- :func:`cpu_s`, :func:`thread_cpu_s`, :func:`machine_cpu`, :func:`idle_share`,
  :func:`rss_mb`, :func:`cmdline`, :func:`children_of`: Linux /proc readers.

The product keeps its own (the demo's children, ``deploy.supervisor``); the
harness imports the product, never the reverse.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

from deploy.unit_policy import set_niceness, unit_nice

_TICK_S = 1.0 / os.sysconf("SC_CLK_TCK")
_PAGE_MB = os.sysconf("SC_PAGE_SIZE") / 2**20


# ------------------------------------------------------------------ starting
def cli_argv(args: list[str]) -> list[str]:
    """The command line of ``deepxpalm ARGS`` run by this interpreter."""
    return [sys.executable, "-m", "deploy.cli", *args]


def spawn_cli(
    args: list[str],
    stdout: IO[Any] | int | None = None,
    *,
    unit: str | None = None,
    in_child: Callable[[], None] | None = None,
    **popen: Any,
) -> subprocess.Popen:
    """``deepxpalm ARGS`` as a child; at the niceness of its systemd ``unit`` when named.

    ``stdout`` is where its output goes (stderr with it unless ``stderr=`` says
    otherwise); ``in_child`` runs in the child before the command (after the
    niceness); every other keyword goes to :class:`subprocess.Popen`.
    """
    nice = unit_nice(unit) if unit is not None else None

    def before() -> None:
        if nice is not None:
            set_niceness(nice)
        if in_child is not None:
            in_child()

    popen.setdefault("stderr", subprocess.STDOUT if stdout is not None else None)
    needs_hook = nice is not None or in_child is not None
    return subprocess.Popen(
        cli_argv(args), stdout=stdout, preexec_fn=before if needs_hook else None, **popen
    )


# ------------------------------------------------------------------ stopping
def stop(
    proc: subprocess.Popen | None,
    timeout_s: float = 15.0,
    sig: int = signal.SIGTERM,
    *,
    group: bool = False,
) -> bool:
    """``sig`` (SIGTERM by default), wait ``timeout_s``, then SIGKILL; True if it was killed.

    ``group``: signal the child's whole process group (a child started with
    ``start_new_session=True`` and its own children, as a browser's). A child
    that has already ended is reaped and left alone. ``timeout_s=0`` kills at once.
    """
    if proc is None or proc.poll() is not None:
        return False

    def send(s: int) -> None:
        with contextlib.suppress(ProcessLookupError):
            if group:
                os.killpg(proc.pid, s)
            else:
                proc.send_signal(s)

    if timeout_s > 0:
        send(sig)
        try:
            proc.wait(timeout=timeout_s)
            return False
        except subprocess.TimeoutExpired:
            pass
    send(signal.SIGKILL)
    proc.wait()
    return True


# ------------------------------------------------------------------ /proc
def _read(path: str) -> str | None:
    try:
        with open(path, "rb") as f:
            return f.read().decode()
    except OSError:  # the process (or thread) has ended
        return None


def _stat_fields(path: str) -> list[str] | None:
    """Fields of a /proc stat file after the command name (which may hold spaces and ')')."""
    text = _read(path)
    if text is None:
        return None
    return text[text.rindex(")") + 2 :].split()


def cpu_s(pid: int) -> float | None:
    """utime + stime of a process (all its threads) in seconds; None once it has ended."""
    fields = _stat_fields(f"/proc/{pid}/stat")
    if fields is None:
        return None
    return (int(fields[11]) + int(fields[12])) * _TICK_S  # stat fields 14 and 15


def process_cpu_s(pid: int) -> float:
    """:func:`cpu_s` of a process that must still run (a node being measured)."""
    seconds = cpu_s(pid)
    if seconds is None:
        raise ProcessLookupError(f"process {pid} has ended: no CPU time to read")
    return seconds


def thread_cpu_s(pid: int) -> dict[str, float]:
    """CPU seconds per thread of a process, keyed "main", or by the thread's OS name + id.

    ZeroMQ names its I/O threads (ZMQbg/...); Python threads all carry the
    interpreter's name, so they are told apart by id only.
    """
    out: dict[str, float] = {}
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return out
    for tid in tids:
        text = _read(f"/proc/{pid}/task/{tid}/stat")
        if text is None:
            continue  # the thread ended
        name = text[text.index("(") + 1 : text.rindex(")")]
        fields = text[text.rindex(")") + 2 :].split()
        key = "main" if tid == str(pid) else f"{name}#{tid}"
        out[key] = (int(fields[11]) + int(fields[12])) * _TICK_S
    return out


def raise_threads(pid: int, nice: int) -> dict[int, int]:
    """Every thread of ``pid`` at niceness ``nice`` or higher (Linux keeps one per thread);
    ``{thread id: its niceness before}`` of those raised. A thread already higher is left
    alone; one that ended meanwhile, or that this process may not raise, keeps its own."""
    raised: dict[int, int] = {}
    try:
        tids = [int(t) for t in os.listdir(f"/proc/{pid}/task")]
    except OSError:  # ended meanwhile
        return raised
    for tid in tids:
        with contextlib.suppress(OSError):
            own = os.getpriority(os.PRIO_PROCESS, tid)
            if own > nice:
                os.setpriority(os.PRIO_PROCESS, tid, nice)
                raised[tid] = own
    return raised


def rss_mb(pid: int) -> float | None:
    """Resident memory of a process in MiB; None once it has ended."""
    text = _read(f"/proc/{pid}/statm")
    if text is None:
        return None
    return int(text.split()[1]) * _PAGE_MB


def cmdline(pid: int) -> list[str] | None:
    """A process's command line; None once it has ended."""
    text = _read(f"/proc/{pid}/cmdline")
    return None if text is None else text.rstrip("\0").split("\0")


def children_of(pid: int) -> list[int]:
    """The processes whose parent is ``pid``."""
    out = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            fields = _stat_fields(f"/proc/{entry}/stat")
            if fields is not None and int(fields[1]) == pid:
                out.append(int(entry))
    return out


def in_session(sid: int) -> list[int]:
    """The processes of the session ``sid`` leads (a process started with ``start_new_session``
    and every process it started, however deep)."""
    out = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            fields = _stat_fields(f"/proc/{entry}/stat")
            if fields is not None and int(fields[3]) == sid:  # state, ppid, pgrp, session
                out.append(int(entry))
    return out


def machine_cpu() -> tuple[float, float]:
    """(idle, total) jiffies of the whole machine since boot (Linux ``/proc/stat``)."""
    fields = [float(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    return fields[3] + fields[4], sum(fields[:8])  # idle + iowait; user .. steal


def idle_share(before: tuple[float, float], after: tuple[float, float]) -> float:
    """Share of the machine's CPU time left idle between two :func:`machine_cpu` readings."""
    total = after[1] - before[1]
    return (after[0] - before[0]) / total if total > 0 else 0.0
