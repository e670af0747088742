"""Signals acted on by a thread of their own, never inside the Python signal handler.

CPython runs a signal handler on the main thread between two bytecodes,
wherever that thread is, including inside a lock it holds. ``Event.set()``
takes the Event's internal lock, and the main thread holds that same lock
for a few bytecodes at both ends of every ``Event.wait()``: a SIGTERM
landing there deadlocks the process, which then ignores every further
SIGTERM while its other threads carry on (the Python docs warn against
locks in handlers). A loop that waits on its stop event with a timeout (the
link simulator waits in 0.1 s steps) runs into that window sooner or later;
the fault matrix measured a ``netsim`` that kept relaying for the 20 s a
clean restart waits and had to be killed.

So the handler here only puts the signal's number on a ``SimpleQueue``, whose
``put`` is reentrant (the documented guarantee that makes it safe in ``__del__``
and here), and a daemon thread takes it off and runs the action.
"""

from __future__ import annotations

import logging
import queue
import signal
import threading
from collections.abc import Callable
from types import FrameType

log = logging.getLogger(__name__)

_pending: queue.SimpleQueue[int] = queue.SimpleQueue()
_actions: dict[int, Callable[[], object]] = {}
_dispatcher: threading.Thread | None = None


def _handler(signum: int, _frame: FrameType | None) -> None:
    _pending.put(signum)  # reentrant: nothing else may happen here


def _dispatch() -> None:
    while True:
        signum = _pending.get()
        action = _actions.get(signum)
        if action is None:
            continue
        try:
            action()
        except Exception:  # a failing action must not end the dispatcher
            log.exception("acting on signal %d failed", signum)


def on_signal(signum: int, action: Callable[[], object]) -> None:
    """Run ``action`` on the dispatcher thread each time ``signum`` arrives.

    Call from the main thread (as ``signal.signal`` must be); a later call
    for the same signal replaces the action.
    """
    global _dispatcher
    _actions[signum] = action
    if _dispatcher is None:
        _dispatcher = threading.Thread(target=_dispatch, name="signals", daemon=True)
        _dispatcher.start()
    signal.signal(signum, _handler)


def stop_on_signals(signums: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)) -> threading.Event:
    """SIGINT and SIGTERM (systemd's stop) set the returned event for a clean shutdown."""
    stop = threading.Event()
    for signum in signums:
        on_signal(signum, stop.set)
    return stop
