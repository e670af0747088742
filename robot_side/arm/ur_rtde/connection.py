"""Opening ur-rtde's two interfaces to a controller, and closing them without a freeze."""

from __future__ import annotations

import contextlib
import ctypes
import gc
import logging
import os
import threading
import time
from collections.abc import Callable
from typing import Any, TypeVar

from common.devices.lifecycle import native_threads_at
from common.devices.preflight import tcp_probe
from common.errors import DeviceNotConnectedError
from robot_side.arm.base import NATIVE_DRIVER_THREAD_NICE
from robot_side.arm.ur_rtde.config import URArmConfig
from robot_side.arm.ur_rtde.control_receiver import CONTROL_THREAD_SLACK_NS

log = logging.getLogger(__name__)

_T = TypeVar("_T")

#: What the receive interface streams: only what this driver reads (less to parse each package).
RECEIVE_VARIABLES = [
    "timestamp",
    "actual_q",
    "actual_TCP_pose",
    "actual_TCP_speed",
    "robot_mode",
    "safety_mode",
    "runtime_state",
    "robot_status_bits",
    "safety_status_bits",
]

#: The receive interface's thread (``receiveCallback``) sleeps 100 us each time its socket has
#: nothing yet, and after 20 empty polls waits in a blocking read: at 125 Hz about 2,700 wakes a
#: second, 6 % of a core at SCHED_FIFO (measured in the arm process). In the fair scheduler with
#: this timer slack a poll comes every 4 ms or so, half the stream's 8 ms period: every package
#: is read before the next arrives, at most 4 ms after the controller sent it (the node reads the
#: pose every 20 ms, the stops their "at rest" within 4 ms more), for about 250 wakes a second.
#: The control interface's thread is made the same way (with the same 4 ms slack), and raised to
#: SCHED_FIFO for the length of every call that waits on it (``control_receiver.py``): kept
#: fair throughout, the keep-alive's period beside two busy loops went from p99.9 20.5 ms
#: (max 21.2) to 23.8 (max 27.9), a real-time kick waiting for a fair thread.
RECEIVE_THREAD_SLACK_NS = 4_000_000
PR_SET_TIMERSLACK, PR_GET_TIMERSLACK = 29, 30

#: ur-rtde's fixed ports on the controller: RTDE, dashboard, the script port.
DASHBOARD_PORT = 29999
CONTROLLER_PORTS = {30004: "RTDE", DASHBOARD_PORT: "dashboard", 30003: "script"}

#: Control interfaces with a call stuck inside (see ``ControlLine.call``), kept so no
#: destructor runs.
ABANDONED: list[Any] = []

#: how long connect() waits for each controller port to accept before calling ur-rtde
PORT_PROBE_TIMEOUT_S = 1.0

#: A controller frees the previous session's RTDE inputs when it sees the
#: close; a reconnect right after a disconnect can arrive first.
CONTROL_CONNECT_TRIES = 5
CONTROL_CONNECT_RETRY_S = 0.2


def open_interfaces(config: URArmConfig) -> tuple[Any, Any, frozenset[int]]:
    """(receive, control) interfaces connected to ``config.host`` and the native threads the
    control interface started, or DeviceNotConnectedError."""
    import rtde_control
    import rtde_receive

    host = config.host
    hint = (
        f"check that the UR controller at {host} is on, reachable (ping it), in remote "
        "control, and that no other program holds its RTDE inputs"
    )
    require_ports_open(host, hint)
    try:
        recv = threads_named(
            "rtde-receive",
            lambda: made_on_fair_thread(
                lambda: rtde_receive.RTDEReceiveInterface(
                    host, config.frequency_hz, RECEIVE_VARIABLES
                ),
                NATIVE_DRIVER_THREAD_NICE,
                RECEIVE_THREAD_SLACK_NS,
            ),
        )
    except RuntimeError as e:
        msg = f"URArm: RTDE receive to {host} failed ({e}); {hint}"
        raise DeviceNotConnectedError(msg) from e
    ctrl, ctrl_tids = None, frozenset()
    for attempt in range(CONTROL_CONNECT_TRIES):
        try:
            # fair with a timer slack, real-time while a call waits on it (control_receiver.py)
            ctrl, ctrl_tids = threads_started(
                "rtde-control",
                lambda: made_on_fair_thread(
                    lambda: rtde_control.RTDEControlInterface(host, config.frequency_hz),
                    NATIVE_DRIVER_THREAD_NICE,
                    CONTROL_THREAD_SLACK_NS,
                ),
            )
            break
        except RuntimeError as e:
            # Right after a disconnect the controller may still hold our previous
            # session's input registers; they are freed when it sees the close.
            if "already in use" in str(e) and attempt + 1 < CONTROL_CONNECT_TRIES:
                log.info("URArm: RTDE inputs at %s still held; trying again", host)
                if attempt == 0:
                    # an exception's traceback can keep our previous interface alive in
                    # cyclic garbage, and only its destructor closes the connection
                    gc.collect()
                time.sleep(CONTROL_CONNECT_RETRY_S)
                continue
            retire(recv)
            msg = f"URArm: RTDE control to {host} failed ({e}); {hint}"
            raise DeviceNotConnectedError(msg) from e
    return recv, ctrl, ctrl_tids


def made_on_fair_thread(make: Callable[[], _T], nice: int, slack_ns: int) -> _T:
    """``make()`` run on a thread of its own in the fair scheduler, at ``nice`` (or the lower
    niceness the caller has) and with a timer slack of ``slack_ns``: the threads it starts
    (ur-rtde's receive loop) are born with the three.

    A thread starts with its creator's policy, niceness and timer slack, and Linux gives a
    real-time thread no timer slack at all (nor one it can set for itself), so a receive
    interface made from the arm process's SCHED_FIFO thread polls every 100 us at SCHED_FIFO.
    Setting another thread's slack needs CAP_SYS_NICE, which the unit does not grant;
    setting one's own never does. ``make``'s exception is raised here.
    """
    out: dict[str, Any] = {}

    def run() -> None:
        tid = threading.get_native_id()
        with contextlib.suppress(OSError):
            # the niceness first (a real-time thread keeps it unused), then the policy
            os.setpriority(os.PRIO_PROCESS, tid, max(nice, os.getpriority(os.PRIO_PROCESS, tid)))
            if os.sched_getscheduler(tid) != os.SCHED_OTHER:
                os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
        set_own_timer_slack_ns(slack_ns)
        try:
            out["made"] = native_threads_at(nice, make)
        except BaseException as e:  # raised on the caller's thread
            out["error"] = e

    thread = threading.Thread(target=run, name="urarm-receive-open", daemon=True)
    thread.start()
    thread.join()
    if "error" in out:
        raise out["error"]
    return out["made"]


def threads_named(name: str, make: Callable[[], _T]) -> _T:
    """``make()``; the threads it started that are not Python's own get ``name`` as their
    name in ``/proc`` and ``top -H`` (a thread may rename any thread of its process)."""
    return threads_started(name, make)[0]


def threads_started(name: str, make: Callable[[], _T]) -> tuple[_T, frozenset[int]]:
    """``make()`` and the native threads it started (named as ``threads_named`` says)."""
    before = _thread_ids()
    made = make()
    python = {t.native_id for t in threading.enumerate()}
    started = frozenset(_thread_ids() - before - python)
    for tid in started:
        with contextlib.suppress(OSError), open(f"/proc/self/task/{tid}/comm", "w") as f:
            f.write(name[:15])  # OSError: it ended meanwhile
    return made, started


def _thread_ids() -> set[int]:
    return {int(t) for t in os.listdir("/proc/self/task")}


def set_own_timer_slack_ns(ns: int) -> bool:
    """The calling thread's timer slack (``PR_SET_TIMERSLACK``); False where it cannot be set
    (not Linux, or a real-time thread, which Linux gives none)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_TIMERSLACK, ctypes.c_ulong(ns), 0, 0, 0)
        return int(libc.prctl(PR_GET_TIMERSLACK, 0, 0, 0, 0)) == ns
    except (OSError, AttributeError):
        return False


def require_ports_open(host: str, hint: str) -> None:
    """Refuse at once when a controller port does not accept a connection.

    ur-rtde's constructors hold the GIL while they connect: against a
    controller that is still booting, or behind a pulled cable (no answer at
    all), every thread of the node would stop until their timeouts. A plain
    socket waits without the GIL, so a reconnect that cannot work yet costs
    the frame loop nothing.
    """
    for port in CONTROLLER_PORTS:
        problem = tcp_probe(host, port, PORT_PROBE_TIMEOUT_S)
        if problem is not None:
            raise DeviceNotConnectedError(f"URArm: {problem}; {hint}")


def close_interfaces(recv: Any, ctrl: Any, broken: str | None) -> None:
    """Close both interfaces; a control interface with a call stuck inside (``broken``) is
    abandoned instead: destroying it would block on that call."""
    if broken is not None:
        log.warning("URArm: control interface abandoned: %s", broken)
        ABANDONED.append(ctrl)
        retire(recv)
    else:
        retire_side_by_side(ctrl, recv)


def retire(interface: Any) -> None:
    """Close an ur-rtde interface and never run its destructor.

    ``disconnect()`` releases the GIL while it sleeps its 0.5 s; the
    destructor sleeps another 0.5 s *holding* it (measured: every other
    thread of the process stops, so a reconnect froze the node's frame loop
    for a second). The object keeps one reference forever: it is never
    destroyed, not even at interpreter exit (where a list of them would cost
    0.5 s each). Closed, it holds no socket and no thread; its memory did not
    show in the process's peak RSS over repeated reconnects.
    """
    try:
        interface.disconnect()
    except RuntimeError as e:  # already gone: nothing left to close
        log.debug("URArm: disconnect of a retired interface: %s", e)
    ctypes.pythonapi.Py_IncRef(ctypes.py_object(interface))


def retire_side_by_side(*interfaces: Any) -> None:
    """``retire`` each interface on a thread of its own, and wait for all of them.

    Each ``disconnect()`` closes its sockets and then sleeps 0.5 s with the GIL
    released, so two retired one after the other cost a second where side by
    side they cost half: a node's stop, and a reconnect, are 0.5 s sooner. The
    controller still sees both connections close 0.5 s before either returns.
    """
    started = []
    for interface in interfaces:
        thread = threading.Thread(target=retire, args=(interface,), name="urarm-retire")
        try:
            thread.start()
        except RuntimeError:  # no new thread at interpreter shutdown: here, in turn
            retire(interface)
            continue
        started.append(thread)
    for thread in started:
        thread.join()
