"""Small test doubles and helpers shared by the system tests."""

from __future__ import annotations

import time

from common.transport import free_loopback_ports


def free_ports(n: int) -> list[int]:
    return free_loopback_ports(n)


class RecordingArm:
    """Stands in for the arm where a test only needs to know what it was told."""

    def __init__(self) -> None:
        self.jogs: list[tuple[float, ...]] = []
        self.jog_times: list[int] = []
        self.stop_times: list[int] = []
        self.is_connected = True

    def connect(self) -> None:
        self.is_connected = True

    def disconnect(self) -> None:
        self.is_connected = False

    def jog(self, velocity) -> None:
        self.jogs.append(tuple(velocity))
        self.jog_times.append(time.monotonic_ns())

    def stop(self) -> None:
        self.stop_times.append(time.monotonic_ns())

    @property
    def stops(self) -> int:
        return len(self.stop_times)
