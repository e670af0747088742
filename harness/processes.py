"""The harness's /proc readers: a process's CPU time, threads, memory, command line, children.

- :func:`cpu_s`, :func:`thread_cpu_s`, :func:`thread_policies`, :func:`machine_cpu`,
  :func:`idle_share`, :func:`rss_mb`, :func:`cmdline`, :func:`children_of`: Linux /proc
  readers.

Starting and stopping a process is the product's own (``deploy.units``: one
spawn, one stop, one readiness), which the harness uses as the demo does.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

_TICK_S = 1.0 / os.sysconf("SC_CLK_TCK")
_PAGE_MB = os.sysconf("SC_PAGE_SIZE") / 2**20


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


def _thread_stats(pid: int) -> Iterator[tuple[str, str, list[str]]]:
    """Each thread of a process that still runs: its key ("main", or its OS name + "#" + id),
    its OS name, and its stat fields after the name."""
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return
    for tid in tids:
        text = _read(f"/proc/{pid}/task/{tid}/stat")
        if text is None:
            continue  # the thread ended
        name = text[text.index("(") + 1 : text.rindex(")")]
        key = "main" if tid == str(pid) else f"{name}#{tid}"
        yield key, name, text[text.rindex(")") + 2 :].split()


def thread_cpu_s(pid: int) -> dict[str, float]:
    """CPU seconds per thread of a process, keyed "main", or by the thread's OS name + id.

    ZeroMQ names its I/O threads (ZMQbg/...); Python threads all carry the
    interpreter's name, so they are told apart by id only.
    """
    return {key: (int(f[11]) + int(f[12])) * _TICK_S for key, _, f in _thread_stats(pid)}


def thread_policies(pid: int) -> dict[str, int]:
    """Each thread's scheduling policy (``os.SCHED_OTHER``, ``os.SCHED_FIFO`` ...), keyed as
    :func:`thread_cpu_s` keys them."""
    return {key: int(f[38]) for key, _, f in _thread_stats(pid)}  # stat field 41


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
