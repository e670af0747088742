"""A pseudo-terminal's round trip inside a saturated session group at a given weight.

    python scripts/pty-latency-under-load.py GROUP_NICE [BUSY_LOOPS]

Starts a session of its own whose scheduling group gets ``GROUP_NICE``
(``/proc/self/autogroup``; root or CAP_SYS_NICE to go below 0), saturates it
with ``BUSY_LOOPS`` busy processes (default 3 on any machine: more than two
cores' worth here), and times 300 one-byte round trips through a pty from
inside it. Prints p50, p99 and the longest, in milliseconds.

Why: the kernel moves a pty's bytes in its own worker threads, which run at
nice 0 outside every session. A group that weighs far more than them and is
busy leaves them little CPU, and every simulated serial device (the servo bus,
the tactile board, the gripper's RTU link) answers late. The Makefile's
``TEST_GROUP_NICE`` is chosen with this.
"""

from __future__ import annotations

import os
import select
import signal
import sys
import threading
import time
import tty

ROUND_TRIPS = 300


def _round_trips() -> list[float]:
    master, slave = os.openpty()
    tty.setraw(slave)

    def echo() -> None:
        while True:
            ready, _, _ = select.select([master], [], [], 1.0)
            if ready:
                os.write(master, os.read(master, 100))

    threading.Thread(target=echo, daemon=True).start()
    out = []
    for _ in range(ROUND_TRIPS):
        t0 = time.perf_counter()
        os.write(slave, b"x")
        select.select([slave], [], [], 5.0)
        os.read(slave, 100)
        out.append((time.perf_counter() - t0) * 1e3)
        time.sleep(0.005)
    return sorted(out)


def main(argv: list[str]) -> int:
    if not argv:
        print(__doc__.strip().splitlines()[2].strip(), file=sys.stderr)
        return 2
    group, loops = int(argv[0]), int(argv[1]) if len(argv) > 1 else 3
    if os.fork():
        _, status = os.wait()
        return os.waitstatus_to_exitcode(status)
    os.setsid()
    try:
        with open("/proc/self/autogroup", "w") as f:
            f.write(str(group))
    except OSError as e:
        print(f"cannot set the group's niceness ({e}); measuring at the one it has")
    busy = []
    for _ in range(loops):
        pid = os.fork()
        if pid == 0:
            while True:
                pass
        busy.append(pid)
    try:
        time.sleep(1.0)
        lat = _round_trips()
    finally:
        for pid in busy:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
    p99 = lat[int(len(lat) * 0.99) - 1]
    print(
        f"group nice {group}, {loops} busy loops: pty round trip p50 {lat[len(lat) // 2]:.2f} ms, "
        f"p99 {p99:.2f} ms, longest {lat[-1]:.1f} ms"
    )
    os._exit(0)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
