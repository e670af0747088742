"""When the arm process dies, the node also presses stop on the controller's dashboard server.

The controller's watchdog stops the arm one window after the arm process's
last kick: that is the guarantee, and it holds whatever the robot node
does. The node notices the death at its next call to the arm (a jog being
renewed, the recovery's check) and presses stop on the dashboard server as
well, as an operator at the pendant would: a controller in remote control
ends the program at once; one that refuses (local control) or does not
answer leaves it to the watchdog. Best effort on a thread of its own: no
loop of the node waits for it.
"""

from __future__ import annotations

import logging
import socket
import threading

from robot_side.arm.ur_rtde.connection import DASHBOARD_PORT

log = logging.getLogger(__name__)
#: connect, the greeting and the answer each get this long
TIMEOUT_S = 0.5


def press_stop(host: str, why: str) -> threading.Thread:
    """``stop`` on ``host``'s dashboard server, on a thread of its own (returned, started)."""
    thread = threading.Thread(
        target=_press, args=(host, why), name="arm-dashboard-stop", daemon=True
    )
    thread.start()
    return thread


def _press(host: str, why: str) -> None:
    try:
        with socket.create_connection((host, DASHBOARD_PORT), timeout=TIMEOUT_S) as sock:
            answers = sock.makefile("rb")
            answers.readline()  # "Connected: Universal Robots Dashboard Server"
            sock.sendall(b"stop\n")
            answer = answers.readline().decode(errors="replace").strip()
    except OSError as e:
        log.warning(
            "arm: %s; the dashboard server at %s:%d did not take a stop (%s): the "
            "controller's watchdog stops the arm",
            why,
            host,
            DASHBOARD_PORT,
            e,
        )
        return
    log.warning("arm: %s; stop pressed on the controller's dashboard: %r", why, answer)
