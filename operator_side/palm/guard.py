"""The palm guard: a process beside the operator node that lifts the palm the moment it ends.

The Feetech servos keep their last goal, so a node killed while a stimulus
pressed the palm leaves the linkages pressing it. ``deepxpalm palm lift``
(the unit's ``ExecStopPost=``) lifts them from a fresh process, but a fresh
Python process is slow to start exactly when it matters: on a saturated
2-core PC its start-up alone took 0.5 to 0.7 s at the unit's ``Nice=-10``.

The guard is that lift, started ahead of time. The node starts it next to
itself (``deepxpalm palm guard``, with the node's own config) and keeps the
write end of a pipe the guard reads. Every end of the node closes that end,
a clean stop, a crash, ``kill -9``, the watchdog's kill alike, and the
guard, its imports done and its config read, opens the bus at once, writes
the retract pose, waits for it and turns torque off: what ``palm lift``
does, without the start-up. It ignores SIGINT, SIGTERM and SIGHUP (a
Ctrl-C in a terminal, systemd's stop of the unit's remaining processes): it
ends once the palm is lifted or the lift failed, at most the bus's wait plus
the arrival's after the node.

It adds to ``ExecStopPost=`` and does not replace it: a guard that died (the
OOM killer, a ``kill -9`` of the whole group) leaves the lift to it, and
``palm lift`` waits while the guard holds the bus (``--wait-for-bus``).
Only a bus that outlives the node has a guard (``kind = "feetech"``).
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

#: how long the guard waits for the bus the node held (its port's lock goes with the node's
#: last file, which the kernel may close after the pipe that woke the guard)
GUARD_BUS_WAIT_S = 2.0


class PalmGuard:
    """The node's side: the guard's process and the pipe whose end wakes it."""

    def __init__(self, process: subprocess.Popen, wake_w: int) -> None:
        self.process = process
        self._wake_w: int | None = wake_w

    @classmethod
    def start(cls, config_path: Path | None, overrides: list[str]) -> PalmGuard:
        """``deepxpalm palm guard`` on the node's config, watching a pipe this process holds."""
        wake_r, wake_w = os.pipe()  # both ends close-on-exec: only the guard gets its own
        try:
            argv = [sys.executable, "-m", "deploy.cli", "palm", "guard", "--watch-fd", str(wake_r)]
            if config_path is not None:
                argv += ["--config", str(config_path)]
            for override in overrides:
                argv += ["--set", override]
            process = subprocess.Popen(argv, stdin=subprocess.DEVNULL, pass_fds=(wake_r,))
        except BaseException:
            os.close(wake_w)
            raise
        finally:
            os.close(wake_r)
        log.info("palm guard: pid %d lifts the palm when this node ends", process.pid)
        return cls(process, wake_w)

    def stop(self) -> None:
        """The node is done with the bus (a clean end): the guard lifts now. A node that dies
        never gets here; the kernel closes the pipe for it."""
        if self._wake_w is not None:
            os.close(self._wake_w)
            self._wake_w = None


def guard(config: Any, watch_fd: int, within_s: float) -> dict[str, Any]:
    """In the guard's process: wait for the node's end on ``watch_fd``, then lift.

    Everything the lift needs is imported and its config read before the wait, so the
    node's end costs only the bus's work.
    """
    from common.devices import lifecycle as devices  # noqa: F401  (each imported now, not after the end)
    from operator_side.palm import lift as palm_lift
    from operator_side.palm import renderer_config  # noqa: F401
    from operator_side.servos import feetech  # noqa: F401

    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)
    while os.read(watch_fd, 64):
        pass  # nothing is ever written: the end of the pipe is the message
    os.close(watch_fd)
    return palm_lift.lift(config, within_s, bus_wait_s=GUARD_BUS_WAIT_S)
