"""Pinning, timers and summaries shared by every benchmark section.

Medians and 99th percentiles of many short repetitions, not means: the
machine is shared, and a mean would be dominated by the few calls that were
preempted. The timer is ``perf_counter_ns`` (monotonic, about 50-100 ns per
read), which is why stages shorter than a microsecond are timed in batches.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from common.process.realtime import ONE_THREAD_POOLS

log = logging.getLogger(__name__)

#: thread variables this process set itself (not the user): child processes
#: that must run as deployed get them removed again
SET_BY_BENCH: list[str] = []
_original_affinity: set[int] | None = None


def limit_thread_pools() -> None:
    """Set ONE_THREAD_POOLS where the user has not; call before numpy (or torch) is imported."""
    for key, value in ONE_THREAD_POOLS.items():
        if key not in os.environ:
            os.environ[key] = value
            SET_BY_BENCH.append(key)


def deployed_env() -> dict[str, str]:
    """This process's environment without the thread limits the bench added."""
    return {k: v for k, v in os.environ.items() if k not in SET_BY_BENCH}


def pin_to_core(cpu: int | None) -> int:
    """Pin this process to one core and return it; None picks the last allowed core.

    The last core is chosen by default because interactive shells and most
    daemons start on core 0; on a shared machine that is only a heuristic.
    """
    global _original_affinity
    allowed = sorted(os.sched_getaffinity(0))
    if _original_affinity is None:
        _original_affinity = set(allowed)
    core = allowed[-1] if cpu is None else cpu
    os.sched_setaffinity(0, {core})
    return core


def original_affinity() -> set[int]:
    """The cores this process could use before pin_to_core."""
    return set(_original_affinity or os.sched_getaffinity(0))


@contextlib.contextmanager
def one_core(cpu: int | None) -> Iterator[int]:
    """Pinned to one core for the block; affinity and torch's threads restored after.

    Restoring matters when the bench runs inside another process (a test
    session), whose later work must not inherit one core.
    """
    before = os.sched_getaffinity(0)
    torch = sys.modules.get("torch")
    torch_threads = torch.get_num_threads() if torch is not None else None
    try:
        yield pin_to_core(cpu)
    finally:
        os.sched_setaffinity(0, before)
        if torch_threads is not None:
            torch.set_num_threads(torch_threads)


def limit_torch_threads() -> None:
    """One intra-op thread in torch, if torch is already loaded (never import it here)."""
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(1)


@dataclass(frozen=True)
class Summary:
    """Microseconds."""

    n: int
    median_us: float
    p90_us: float
    p99_us: float
    max_us: float
    mean_us: float

    def as_dict(self) -> dict[str, float]:
        return {
            "n": self.n,
            "median_us": self.median_us,
            "p90_us": self.p90_us,
            "p99_us": self.p99_us,
            "max_us": self.max_us,
            "mean_us": self.mean_us,
        }


def summarize_ns(samples_ns: np.ndarray | list[int]) -> Summary:
    """Median, p90, p99, max and mean of samples in nanoseconds, as microseconds."""
    a = np.asarray(samples_ns, dtype=np.float64) / 1e3
    if a.size == 0:
        nan = float("nan")
        return Summary(0, nan, nan, nan, nan, nan)
    p50, p90, p99 = np.percentile(a, [50, 90, 99])
    return Summary(int(a.size), float(p50), float(p90), float(p99), float(a.max()), float(a.mean()))


def time_calls(fn: Callable[[int], Any], n: int, warmup: int = 100, batch: int = 1) -> np.ndarray:
    """Nanoseconds per call of ``fn(i)`` for i in range(n), each sample a batch of calls.

    ``batch`` > 1 divides one timer reading over several calls, for stages
    so short that the timer itself would dominate; the p99 of batched
    samples is then an underestimate of a single call's tail.
    """
    for i in range(warmup):
        fn(i)
    clock = time.perf_counter_ns
    out = np.empty(n, dtype=np.int64)
    if batch == 1:
        for i in range(n):
            t = clock()
            fn(i)
            out[i] = clock() - t
        return out
    for i in range(n):
        t = clock()
        for j in range(batch):
            fn(i * batch + j)
        out[i] = (clock() - t) // batch
    return out


def time_interleaved(
    fns: list[Callable[[int], Any]], n: int, warmup: int = 100, gap_s: float = 0.0
) -> list[np.ndarray]:
    """Nanoseconds per call of each ``fn(i)``, the functions taking turns call by call.

    On a shared machine the load drifts over seconds; timing alternatives in
    turn gives each the same conditions, so their difference is theirs, not
    the drift's (timing them one block after another is not comparable).
    ``gap_s`` sleeps before every call, as a node sleeps between frames: each
    call then meets the cold caches it meets in the field.
    """
    for i in range(warmup):
        for fn in fns:
            fn(i)
    clock = time.perf_counter_ns
    out = [np.empty(n, dtype=np.int64) for _ in fns]
    for i in range(n):
        for k, fn in enumerate(fns):
            if gap_s > 0:
                time.sleep(gap_s)
            t = clock()
            fn(i)
            out[k][i] = clock() - t
    return out


def timer_overhead_ns(n: int = 10000) -> float:
    """Median cost of one pair of timer reads, to state next to sub-microsecond stages."""
    clock = time.perf_counter_ns
    out = np.empty(n, dtype=np.int64)
    for i in range(n):
        t = clock()
        out[i] = clock() - t
    return float(np.median(out))


def wakeup_cpu_us(rate_hz: float = 240.0, seconds: float = 2.0) -> float:
    """CPU microseconds one sleeping thread spends per wake-up on this machine.

    The nodes wake several threads per frame (serial reader, node loop,
    ZeroMQ's I/O thread); where a wake-up is expensive (a VM's timer and
    scheduler paths), that, not the computation, sets their CPU share.
    """
    import threading

    stop = threading.Event()
    box: list[int] = []

    def sleeper() -> None:
        period = 1.0 / rate_hz
        c0 = time.thread_time_ns()
        n = 0
        while not stop.is_set():
            time.sleep(period)
            n += 1
        box.extend([time.thread_time_ns() - c0, n])

    th = threading.Thread(target=sleeper, name="bench-wakeups", daemon=True)
    th.start()
    time.sleep(seconds)
    stop.set()
    th.join()
    cpu_ns, n = box
    return cpu_ns / max(1, n) / 1e3


def cold_call_us(gap_s: float = 0.008, n: int = 150) -> dict[str, float]:
    """One pure-Python IK call back to back, and the first one after an idle gap (us).

    The gap is spent spinning on the clock, so the thread never leaves the
    core: what the first call pays is the state the core lost meanwhile
    (caches, TLB, branch predictors), which is what a node pays per frame.
    """
    from operator_side.palm.linkglide import inverse_kinematics_one

    clock = time.perf_counter_ns
    warm, cold = [], []
    for _ in range(n):
        end = time.perf_counter() + gap_s
        while time.perf_counter() < end:
            pass
        t = clock()
        inverse_kinematics_one(10.0, 58.0)
        t1 = clock()
        inverse_kinematics_one(10.0, 58.0)
        inverse_kinematics_one(10.0, 58.0)
        t2 = clock()
        cold.append(t1 - t)
        warm.append((t2 - t1) / 2)
    return {
        "gap_ms": gap_s * 1e3,
        "warm_us": float(np.median(warm)) / 1e3,
        "first_after_gap_us": float(np.median(cold)) / 1e3,
    }


def full_collection_ms() -> dict[str, float]:
    """A full cyclic-GC pass over this process's heap, as is and frozen (the nodes freeze it).

    Measured in the bench process with the robot stack loaded; the freeze is
    undone afterwards, so the rest of the bench runs as before.
    """
    import gc

    gc.collect()
    objects = len(gc.get_objects())
    t = time.perf_counter()
    gc.collect()
    as_is = time.perf_counter() - t
    gc.freeze()
    try:
        t = time.perf_counter()
        gc.collect()
        frozen = time.perf_counter() - t
    finally:
        gc.unfreeze()
    return {"objects": float(objects), "as_is_ms": as_is * 1e3, "frozen_ms": frozen * 1e3}


def machine_load() -> dict[str, Any]:
    """Load averages and core count, to print beside every number taken on a shared machine."""
    one, five, fifteen = os.getloadavg()
    return {
        "loadavg_1m": round(one, 2),
        "loadavg_5m": round(five, 2),
        "loadavg_15m": round(fifteen, 2),
        "cpu_count": os.cpu_count(),
    }
