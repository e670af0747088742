"""Opening ur-rtde's two interfaces to a controller, and closing them without a freeze."""

from __future__ import annotations

import ctypes
import gc
import logging
import threading
import time
from typing import Any

from common.devices import native_threads_at
from common.errors import DeviceNotConnectedError
from common.preflight import tcp_probe
from robot_side.arm.base import NATIVE_DRIVER_THREAD_NICE
from robot_side.arm.ur_rtde.config import URArmConfig

log = logging.getLogger(__name__)

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

#: ur-rtde's fixed ports on the controller: RTDE, dashboard, the script port.
CONTROLLER_PORTS = {30004: "RTDE", 29999: "dashboard", 30003: "script"}

#: Control interfaces with a call stuck inside (see ``ControlLine.call``), kept so no
#: destructor runs.
ABANDONED: list[Any] = []

#: how long connect() waits for each controller port to accept before calling ur-rtde
PORT_PROBE_TIMEOUT_S = 1.0

#: A controller frees the previous session's RTDE inputs when it sees the
#: close; a reconnect right after a disconnect can arrive first.
CONTROL_CONNECT_TRIES = 5
CONTROL_CONNECT_RETRY_S = 0.2


def open_interfaces(config: URArmConfig) -> tuple[Any, Any]:
    """(receive, control) interfaces connected to ``config.host``, or DeviceNotConnectedError."""
    import rtde_control
    import rtde_receive

    host = config.host
    hint = (
        f"check that the UR controller at {host} is on, reachable (ping it), in remote "
        "control, and that no other program holds its RTDE inputs"
    )
    require_ports_open(host, hint)
    try:
        recv = native_threads_at(
            NATIVE_DRIVER_THREAD_NICE,
            lambda: rtde_receive.RTDEReceiveInterface(host, config.frequency_hz, RECEIVE_VARIABLES),
        )
    except RuntimeError as e:
        msg = f"URArm: RTDE receive to {host} failed ({e}); {hint}"
        raise DeviceNotConnectedError(msg) from e
    ctrl = None
    for attempt in range(CONTROL_CONNECT_TRIES):
        try:
            ctrl = native_threads_at(
                NATIVE_DRIVER_THREAD_NICE,
                lambda: rtde_control.RTDEControlInterface(host, config.frequency_hz),
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
    return recv, ctrl


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
