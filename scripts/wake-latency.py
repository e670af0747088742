"""How late a thread that sleeps 5 ms at a time wakes, at a niceness or real-time.

    python scripts/wake-latency.py nice NICE SECONDS
    python scripts/wake-latency.py fifo PRIORITY SECONDS

Runs for ``SECONDS`` in a session of its own. ``nice``: at niceness ``NICE``,
its session's scheduling group (``/proc/self/autogroup``) at ``NICE`` too, so
it weighs as much as any session on the machine (root or CAP_SYS_NICE to go
below 0). ``fifo``: at SCHED_FIFO ``PRIORITY`` (root, or an RLIMIT_RTPRIO that
allows it), ahead of every thread of the fair scheduler. Run it beside the
load you care about (a lab trial, the suite's deployment lane, a robot PC's
desktop) and compare the two: it prints how many wakes it made and how late
they came (p50, p99, the longest, how many after 40 ms and after 150 ms, the
UR controller's watchdog window).

Why: the arm's safety threads (the deadman and the keep-alive that kicks the
controller's watchdog) sleep between short turns and need the CPU the moment
they wake. A niceness ranks a thread only against the threads it competes
with in the fair scheduler; ``docs/deploy.md`` ("Real-time scheduling") says
when the robot node may run real-time instead. Its writes go to standard
output once, at the end, so that no write of its own can hold it up.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

PERIOD_S = 0.005


def _enter(policy: str, value: int) -> str:
    """Put this process where ``policy`` says; a line saying where it runs."""
    os.setsid()  # a session, and so a scheduling group, of its own
    if policy == "nice":
        try:
            os.setpriority(os.PRIO_PROCESS, 0, value)
            Path("/proc/self/autogroup").write_text(str(value))
        except OSError as e:
            sys.exit(f"cannot run at nice {value} here ({e}): run as root or with CAP_SYS_NICE")
        return f"nice {value}, its session's group at {value}"
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(value))
    except (OSError, AttributeError) as e:
        sys.exit(f"cannot run at SCHED_FIFO {value} here ({e}): run as root or raise RLIMIT_RTPRIO")
    return f"SCHED_FIFO {value}"


def _late_wakes(seconds: float) -> list[float]:
    """Each wake's lateness past its 5 ms sleep, in seconds."""
    late = []
    t_end = time.monotonic() + seconds
    before = time.monotonic()
    while before < t_end:
        time.sleep(PERIOD_S)
        after = time.monotonic()
        late.append(after - before - PERIOD_S)
        before = after
    return late


def main() -> None:
    if len(sys.argv) != 4 or sys.argv[1] not in ("nice", "fifo"):
        sys.exit(__doc__.split("\n\n")[1])
    policy, value, seconds = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
    pid = os.fork()  # a process group's leader (a shell's job) cannot start a session
    if pid:
        sys.exit(os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1]))
    where = _enter(policy, value)
    late = sorted(_late_wakes(seconds))
    n = len(late)
    ms = [x * 1e3 for x in late]
    print(
        f"{where}: {n} wakes in {seconds:g} s; late p50 {ms[n // 2]:.2f} ms, "
        f"p99 {ms[min(n - 1, int(n * 0.99))]:.2f} ms, longest {ms[-1]:.1f} ms; "
        f"{sum(x > 40 for x in ms)} after 40 ms, {sum(x > 150 for x in ms)} after 150 ms"
    )


if __name__ == "__main__":
    main()
