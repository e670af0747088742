"""The lifecycle every device shares, real driver or simulator alike.

A device is built from its typed config, does no I/O until ``connect()``,
and raises ``DeviceNotConnectedError`` when used outside that window. Nodes
only ever talk to these interfaces, so swapping a scripted source for a
serial driver against a pseudo-terminal simulator touches no node code.

A device also describes itself to ``deepxpalm doctor``: ``simulated`` says
there is no hardware behind it, ``location()`` where its hardware is, and
``preflight()`` what is wrong there before the driver opens it.
"""

from __future__ import annotations

import abc
import contextlib
import functools
import importlib
import logging
import os
import threading
from collections.abc import Callable, Mapping
from typing import Any, ClassVar, Self, TypeVar

from common.config.typed import from_dict
from common.devices.preflight import Finding, PreflightContext
from common.errors import ConfigError, DeviceNotConnectedError

log = logging.getLogger(__name__)
_T = TypeVar("_T")


class Device(abc.ABC):
    """Base class: ``connect``/``disconnect``/``is_connected`` and ``with`` support."""

    #: Typed config dataclass for this kind of device (set by subclasses).
    Config: ClassVar[type]
    #: Human-readable family name used in error messages ("tactile sensor").
    family: ClassVar[str] = "device"
    #: True when no hardware sits behind it (a simulator, a memory fake, the lab world).
    simulated: ClassVar[bool] = False

    @abc.abstractmethod
    def connect(self) -> None: ...

    @abc.abstractmethod
    def disconnect(self) -> None: ...

    @property
    @abc.abstractmethod
    def is_connected(self) -> bool: ...

    def require_connected(self) -> None:
        if not self.is_connected:
            raise DeviceNotConnectedError(
                f"{self.family} {type(self).__name__} is not connected: call connect() first"
            )

    def preflight(self, context: PreflightContext) -> list[Finding]:
        """Problems with the hardware found without opening the driver; empty: go ahead.

        A simulated device has no hardware to look for. Drivers override
        ``_preflight`` (``common.devices.preflight`` has the serial and TCP checks).
        """
        if self.simulated:
            return []
        return self._preflight(context)

    def _preflight(self, context: PreflightContext) -> list[Finding]:
        return []

    def location(self) -> str:
        """Where the hardware is, for reports ("on /dev/ttyACM0 at 921600 baud"); "" if none."""
        if self.simulated:
            return ""
        return self._location()

    def _location(self) -> str:
        return ""

    def status(self) -> dict[str, Any]:
        """A small JSON-able summary for `deepxpalm devices` and the live view."""
        return {"kind": type(self).__name__, "connected": self.is_connected}

    def __enter__(self) -> Self:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.disconnect()


def load_object(target: str) -> Any:
    """Import ``"package.module:Name"`` lazily, so unused kinds are never imported."""
    module_name, _, attr = target.partition(":")
    return getattr(importlib.import_module(module_name), attr)


#: Device kinds renamed: the old name is refused with the new one, so that a config names
#: what it builds ("recording" servos recorded nothing; they keep the goals in memory).
RENAMED_KINDS = {"recording": "in_memory"}


def build_device(registry: Mapping[str, str], section: Mapping[str, Any], where: str) -> Device:
    """Build the device a config section names by its ``kind`` key.

    ``registry`` maps kind names to ``"module:Class"``; the class's ``Config``
    dataclass parses the rest of the section.
    """
    kind = section.get("kind")
    if kind not in registry and RENAMED_KINDS.get(kind) in registry:
        raise ConfigError(
            f"{where}.kind = {kind!r} has been renamed: write kind = {RENAMED_KINDS[kind]!r}"
        )
    if kind not in registry:
        raise ConfigError(
            f"{where}.kind = {kind!r} is not a known kind; choose one of {sorted(registry)}"
        )
    cls = load_object(registry[kind])
    rest = {k: v for k, v in section.items() if k != "kind"}
    config = from_dict(cls.Config, rest, where=where)
    log.debug("building %s kind %s", where, kind)
    return cls(config)


#: The priority of a simulator that stands for hardware (a controller, a board, a servo bus,
#: the lab's physics): hardware never waits for the PC's CPU, so its simulator runs at the
#: robot node's priority (Nice=-10) where it may (root, CAP_SYS_NICE), and a busy machine
#: slows the nodes under test, not the devices they are judged by.
SIMULATED_HARDWARE_NICE = -10


def at_niceness(nice: int, target: Callable[..., Any]) -> Callable[..., Any]:
    """A thread's ``target``, run at niceness ``nice`` where the process may raise it.

    Linux keeps a niceness per thread, and a thread starts at its creator's, so
    the threads it starts (a connection's) run at ``nice`` too. A thread that
    already runs higher (a process started at -15) keeps its own. Without root or
    CAP_SYS_NICE the thread keeps the priority it has: the same program, less margin.
    When ``target`` returns, the thread gets its own niceness back (a caller that ran it
    in place, not on a thread of its own, goes on at its priority).
    """

    @functools.wraps(target)
    def run(*args: Any, **kwargs: Any) -> Any:
        tid = threading.get_native_id()
        own = os.getpriority(os.PRIO_PROCESS, tid)
        with contextlib.suppress(OSError):
            os.setpriority(os.PRIO_PROCESS, tid, min(nice, own))
        try:
            return target(*args, **kwargs)
        finally:
            with contextlib.suppress(OSError):
                os.setpriority(os.PRIO_PROCESS, tid, own)

    return run


def native_threads_at(nice: int, make: Callable[[], _T]) -> _T:
    """``make()``; the threads it started that are not Python's own run at ``nice`` or lower.

    A C++ library's threads (ur-rtde's receive loops) start at their creator's niceness and
    never take the interpreter lock, so they need not share the priority of the Python
    threads around them; lowering a thread is always allowed. A Python thread started
    meanwhile by another thread is recognised by its native id and left alone.
    """
    before = _thread_ids()
    made = make()
    python = {t.native_id for t in threading.enumerate()}
    for tid in _thread_ids() - before - python:
        with contextlib.suppress(OSError):  # ended meanwhile
            if os.getpriority(os.PRIO_PROCESS, tid) < nice:
                os.setpriority(os.PRIO_PROCESS, tid, nice)
    return made


def _thread_ids() -> set[int]:
    return {int(t) for t in os.listdir("/proc/self/task")}


def as_hardware(target: Callable[..., Any]) -> Callable[..., Any]:
    """A simulator thread's ``target``, run at :data:`SIMULATED_HARDWARE_NICE` where it may.

    A simulator served from a driver's or a test's process outranks that
    process's other threads and everything at ordinary priority.
    """
    return at_niceness(SIMULATED_HARDWARE_NICE, target)


class OnItsSimulator(abc.ABC):
    """Mixin for a simulated kind: the real driver, connected to a simulator it owns.

    ``connect`` starts the simulator and points the driver's config at it
    (``_start_simulator``) before the driver's own ``connect``; the
    simulator stops again if either fails, and after the driver's
    ``disconnect`` (clients first: a simulator that vanishes under a driver
    makes it retry). Put it first in the bases: ``class SimulatedX(OnItsSimulator, XDriver)``.
    """

    simulated: ClassVar[bool] = True

    @abc.abstractmethod
    def _start_simulator(self) -> None:
        """Start the simulator if it is not running, and point ``self.config`` at it."""

    @abc.abstractmethod
    def _stop_simulator(self) -> None:
        """Stop the simulator; safe when it is not running or only half started."""

    def find_device(self) -> None:
        """Where the driver connects: the simulator started (a driver run elsewhere, as an
        arm process, is pointed at it by whoever holds this object)."""
        self._start_simulator()

    def release_device(self) -> None:
        self._stop_simulator()

    def connect(self) -> None:
        try:
            self._start_simulator()
            super().connect()  # type: ignore[misc]
        except BaseException:
            self._stop_simulator()
            raise

    def disconnect(self) -> None:
        try:
            super().disconnect()  # type: ignore[misc]
        finally:
            self._stop_simulator()

    def reconnect_driver(self) -> None:
        """Drop and reopen the driver's connection; the simulator keeps running.

        A real controller, gripper or bus stays up while its driver recovers,
        and so does its simulator: restarting it would reset the arm's pose
        and cost a process start-up (seconds on a loaded machine) inside the
        recovery. A simulator that died meanwhile is started again.
        """
        try:
            super().disconnect()  # type: ignore[misc]
        except Exception:  # a half-dead driver may fail to close; connect decides
            log.debug("%s: disconnect before reconnect failed", type(self).__name__, exc_info=True)
        self.connect()
