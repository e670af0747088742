"""ur-rtde's control receive thread: fair between calls, real-time while a call waits on it.

The control interface's thread (``receiveCallback``) reads the controller's
stream for the script's answers: it sleeps 100 us whenever its socket has
nothing yet and waits in a blocking read after 20 empty polls, so at 125 Hz
it wakes about 2,700 times a second. At SCHED_FIFO that was the arm process's
largest cost (3.5 to 6 % of a core on a VM), although only a call in flight (a
kick, a stop, a move's handshake) waits for what it reads.

So it is made in the fair scheduler with a timer slack (a poll every 4 ms or
so, half the stream's period as for the receive interface's thread, about
350 wakes a second; at 2 ms, 500) and raised to SCHED_FIFO for the length of each
call that waits on it, one step under the keep-alive as before; a call's
answer then comes at most one slack later than at SCHED_FIFO throughout,
and no busy loop of the machine's delays it. Linux gives a thread back its
creator's timer slack when it leaves SCHED_FIFO, so the slack holds between
calls. Where SCHED_FIFO is refused (no ``LimitRTPRIO=``), the thread stays
fair and the calls wait on it as on any other thread.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
from collections.abc import Iterator

log = logging.getLogger(__name__)

#: the control receive thread's timer slack between calls: its polls come about this often
CONTROL_THREAD_SLACK_NS = 4_000_000


class ControlReceiver:
    """The native threads ur-rtde's control interface started (``tids``), raised to
    SCHED_FIFO ``priority`` while a call waits on them (0: never)."""

    def __init__(self, tids: frozenset[int] = frozenset(), priority: int = 0) -> None:
        self.tids = tids
        self.priority = priority
        self.refused: str | None = None  # why SCHED_FIFO was refused, once (then never asked)
        self._lock = threading.Lock()
        self._holders = 0  # blocks inside ``realtime`` now (a kick beside a command's call)
        self._raised: list[int] = []

    @contextlib.contextmanager
    def realtime(self) -> Iterator[None]:
        """The threads at SCHED_FIFO for the block, fair again once no block holds them: a
        kick that finds a command on the wire does not lower them under that command."""
        if self.priority <= 0 or self.refused is not None or not self.tids:
            yield
            return
        with self._lock:
            self._holders += 1
            if self._holders == 1:
                self._raised = self._raise()
        try:
            yield
        finally:
            with self._lock:
                self._holders -= 1
                if self._holders == 0:
                    self._lower()

    def close(self) -> None:
        """The interface is closing: its threads end, and their ids may soon be another
        process's. Nothing is raised from here on (the raises and this hold one lock), so
        no call needs to look them up in ``/proc`` first (32 us a kick, on a VM)."""
        with self._lock:
            self.tids = frozenset()
            self._lower()

    def _lower(self) -> None:
        """The raised threads fair again; call with the lock held."""
        for tid in self._raised:
            with contextlib.suppress(OSError):
                os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
        self._raised = []

    def _raise(self) -> list[int]:
        raised = []
        for tid in self.tids:
            try:
                os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(self.priority))
                raised.append(tid)
            except ProcessLookupError:  # it ended meanwhile
                continue
            except OSError as e:
                self.refused = e.strerror or str(e)
                log.warning(
                    "URArm: ur-rtde's control thread may not run real-time (%s): the "
                    "controller's answers wait for a fair thread",
                    self.refused,
                )
                break
        return raised
