"""The UR simulator in a child process (``robot_side.stdio_child``), remote-controlled.

ur-rtde's interface constructors hold the GIL while they wait for the
controller's replies, so a simulator served by threads of the same
interpreter can never answer them (measured: the constructor deadlocks).
A child process also makes "the controller vanished" real: :meth:`kill`
takes it away as abruptly as a pulled cable.
"""

from __future__ import annotations

import logging
from typing import IO, Any

import numpy as np

from common.devices.lifecycle import SIMULATED_HARDWARE_NICE
from common.process.realtime import ONE_THREAD_POOLS
from robot_side.arm.sim.server import URSimConfig, URSimulator
from robot_side.devices.stdio_child import StdioChild
from robot_side.devices.stdio_child import serve_stdio as serve_child

log = logging.getLogger(__name__)

#: Simulator methods the parent may call through the pipe.
REMOTE_METHODS = frozenset(
    {
        "freeze",
        "hang_script",
        "protective_stop",
        "unlock_protective_stop",
        "tcp_pose",
        "tcp_speed",
        "mode_name",
        "commands_seen",
        "command_events",
        "at_rest_since",
        "stats",
    }
)


def serve_stdio(sim: URSimulator, stdin: IO[str], stdout: IO[str]) -> None:
    """The child's side: answer requests until stdin closes or "stop" arrives."""
    serve_child(sim, REMOTE_METHODS, sim.host, stdin, stdout, on_exit=sim.stop)


class URSimProcess(StdioChild):
    """Start with :meth:`start`; ``host`` is then the address the simulator serves."""

    def __init__(self, config: URSimConfig | None = None, log_level: int = logging.WARNING):
        # a controller is hard real time: it never waits for the PC's CPU
        super().__init__(
            "robot_side.arm.sim",
            config or URSimConfig(),
            "UR simulator",
            log_level,
            nice=SIMULATED_HARDWARE_NICE,
            env=ONE_THREAD_POOLS,  # real-time where granted (__main__): no pool may spin
        )
        self.host: str | None = None

    def start(self, timeout_s: float = 15.0) -> URSimProcess:
        self.host = self.start_child(timeout_s)
        log.info("UR simulator process %s serving on %s", self.pid, self.host)
        return self

    # convenience wrappers for tests and the demo
    def freeze(self, frozen: bool = True) -> None:
        self.call("freeze", frozen)

    def hang_script(self, hung: bool = True) -> None:
        self.call("hang_script", hung)

    def protective_stop(self) -> None:
        self.call("protective_stop")

    def unlock_protective_stop(self) -> None:
        self.call("unlock_protective_stop")

    def tcp_pose(self) -> np.ndarray:
        return np.asarray(self.call("tcp_pose"))

    def tcp_speed(self) -> np.ndarray:
        return np.asarray(self.call("tcp_speed"))

    def mode_name(self) -> str:
        return self.call("mode_name")

    def commands_seen(self) -> list[int]:
        return self.call("commands_seen")

    def command_events(self, since_s: float = 0.0) -> list[tuple[float, int, str]]:
        """As ``URSimulator.command_events`` (monotonic seconds: every process shares them)."""
        return [tuple(e) for e in self.call("command_events", since_s)]

    def at_rest_since(self, linear_m_s: float, angular_rad_s: float) -> float | None:
        """As ``URSimulator.at_rest_since``: when the arm came to rest, by the controller."""
        return self.call("at_rest_since", linear_m_s, angular_rad_s)

    def stats(self) -> dict[str, Any]:
        return self.call("stats")

    def __enter__(self) -> URSimProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
