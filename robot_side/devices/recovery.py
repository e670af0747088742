"""Bring a failed device back without stalling the loop that uses it.

A driver that gives up (the UR control interface abandoned after a call
missed its deadline, a gripper socket reset) stays down until it is
disconnected and connected again. That takes up to a second or two, so it
happens on a background thread with a growing back-off, and the node treats
the device as unavailable meanwhile: commands for it are refused and
counted, never queued.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any

from common.errors import DeviceError

log = logging.getLogger(__name__)


class DeviceRecovery:
    def __init__(
        self,
        device: Any,
        name: str,
        stop: threading.Event,
        first_backoff_s: float = 0.5,
        max_backoff_s: float = 10.0,
    ) -> None:
        self.device = device
        self.name = name
        self._stop = stop
        self._first = first_backoff_s
        self._max = max_backoff_s
        self._available = threading.Event()
        self._available.set()
        self._thread: threading.Thread | None = None
        self.failures = 0
        self.recoveries = 0

    @property
    def available(self) -> bool:
        return self._available.is_set()

    def call(self, fn: Callable[..., Any], *args: Any) -> Any:
        """Run a device call; a ``DeviceError`` from a dead driver starts a recovery.

        The error is always re-raised to the caller.
        """
        if not self._available.is_set():
            raise DeviceError(f"{self.name} is reconnecting after a failure")
        try:
            return fn(*args)
        except DeviceError:
            if self.needs_reconnect():  # a refused or timed-out call alone is not a dead driver
                self.failed()
            raise

    def needs_reconnect(self) -> bool:
        """The driver lost its connection, or says it must be connected again."""
        device = self.device
        return not device.is_connected or bool(getattr(device, "needs_reconnect", False))

    def failed(self) -> None:
        if self._thread is not None and self._thread.is_alive():
            return
        self.failures += 1
        self._available.clear()
        self._thread = threading.Thread(
            target=self._recover, name=f"recover-{self.name}", daemon=True
        )
        self._thread.start()

    def _recover(self) -> None:
        backoff = self._first
        while not self._stop.wait(backoff):
            try:
                self._reconnect()
            except Exception as e:  # any failure: try again later
                backoff = min(self._max, backoff * 2)
                log.warning("%s: reconnect failed (%s); next try in %.1f s", self.name, e, backoff)
                continue
            self.recoveries += 1
            log.info("%s: reconnected", self.name)
            self._available.set()
            return

    def _reconnect(self) -> None:
        reconnect_driver = getattr(self.device, "reconnect_driver", None)
        if reconnect_driver is not None:  # a simulated device: its simulator stays up
            reconnect_driver()
            return
        try:
            self.device.disconnect()
        except Exception:  # a half-dead driver may fail to close; connect decides
            log.debug("%s: disconnect before reconnect failed", self.name, exc_info=True)
        self.device.connect()

    def join(self, timeout_s: float = 5.0) -> None:
        if self._thread is not None:
            self._thread.join(timeout_s)
