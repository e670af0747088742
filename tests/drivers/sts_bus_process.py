"""The fake STS bus served from a process of its own, for the driver tests.

Served from a thread of the test's own process, the simulator shares that
process's GIL with the driver under test, and on a lane of four workers its
replies came 300 ms late now and then, with both threads at the same
priority: a test failure that says nothing about the driver. A servo bus is a
device of its own, so here it is one: a ``multiprocessing`` manager process
(forked from a forkserver, at the simulated hardware's priority) holds the
real ``FakeStsBus``, and the test reaches it through a proxy.
"""

from __future__ import annotations

import functools
import multiprocessing
from multiprocessing.managers import BaseManager
from typing import Any

from common.devices.lifecycle import SIMULATED_HARDWARE_NICE
from deploy.units.policy import set_niceness
from operator_side.servos.sts_sim import FakeStsBus, FakeStsBusConfig


class _Served(FakeStsBus):
    """What a proxy can reach: methods only, and nothing that returns the bus itself."""

    def begin(self) -> None:
        self.start()

    def port_name(self) -> str:
        return self.port

    def goal_log_list(self) -> list[tuple[int, int, int]]:
        return list(self.goal_log)


class _Manager(BaseManager):
    pass


_Manager.register("FakeStsBus", _Served)

_CONTEXT = multiprocessing.get_context("forkserver")
_CONTEXT.set_forkserver_preload(["operator_side.servos.sts_sim"])


class FakeStsBusProcess:
    """``FakeStsBus``'s test API, served from another process; a context manager."""

    def __init__(self, config: FakeStsBusConfig | None = None) -> None:
        self._manager = _Manager(ctx=_CONTEXT)
        self._manager.start(functools.partial(set_niceness, SIMULATED_HARDWARE_NICE))
        self._bus: Any = self._manager.FakeStsBus(config)  # type: ignore[attr-defined]
        self.port = ""

    def __enter__(self) -> FakeStsBusProcess:
        self._bus.begin()
        self.port = self._bus.port_name()
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            self._bus.stop()
        finally:
            self._manager.shutdown()

    @property
    def goal_log(self) -> list[tuple[int, int, int]]:
        return self._bus.goal_log_list()

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_"):  # not the bus's: no lookup through a proxy not yet made
            raise AttributeError(name)
        return getattr(self._bus, name)
