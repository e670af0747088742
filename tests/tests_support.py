"""Small test doubles and helpers shared by the system tests."""

from __future__ import annotations

import socket
import time


def free_ports(n: int) -> list[int]:
    socks = []
    for _ in range(n):
        s = socket.socket()
        s.bind(("127.0.0.1", 0))
        socks.append(s)
    ports = [s.getsockname()[1] for s in socks]
    for s in socks:
        s.close()
    return ports


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
