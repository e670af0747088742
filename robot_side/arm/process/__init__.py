"""The arm's real-time duties in a process of their own (``ArmProcess``), and the kinds using it.

Why: the UR controller stops the arm when the robot PC is silent longer than
its watchdog window (150 ms). Inside the robot node the keep-alive that
kicks it shares one interpreter lock with the frame loop, inference, the
link and the dashboard: on a busy PC it was measured waking 347 ms late,
and a real-time thread there would still wait for the lock. So the driver
(ur-rtde's two interfaces, the deadman that ends a jog nobody renews, the
keep-alive, the stops, the pose read back) runs in a small process of its
own whose keep-alive thread is raised to SCHED_FIFO where the unit grants
it (``LimitRTPRIO=``), and at the safety threads' niceness where it does
not (``doctor`` says which).

The robot node holds an ``ArmProcess``: an ``Arm`` whose calls go through
a pipe (JSON lines, ``robot_side.stdio_child``) and whose newest pose and
state come from shared memory (``state.py``), read without waiting. If the
node dies the process stops the arm at once and ends; if the process dies,
the controller's watchdog stops the arm, and the node's recovery starts a
new one (``needs_reconnect``).

``KINDS`` in ``robot_side.arm`` names the classes here: each builds its
driver inline when ``own_process = false`` (the old layout, measured beside
the new in the bench), and an ``ArmProcess`` running it otherwise.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from common.clocks.clock import now_s
from common.config.typed import to_dict
from common.devices.lifecycle import Device
from common.devices.preflight import Finding, PreflightContext
from common.errors import (
    DeviceAlreadyConnectedError,
    DeviceError,
    DeviceNotConnectedError,
    DeviceTimeoutError,
)
from common.process.realtime import ONE_THREAD_POOLS
from robot_side.arm.base import Arm, as_vector6, turn_angle
from robot_side.arm.process.child import ArmProcessSpec
from robot_side.arm.process.dashboard_stop import press_stop
from robot_side.arm.process.errors import as_driver_error
from robot_side.arm.process.state import (
    StateView,
    keep_alive_of,
    live_of,
    new_state_file,
    telemetry_of,
)
from robot_side.devices.stdio_child import StdioChild

log = logging.getLogger(__name__)

#: the arm process's first line (the driver built, its state writer running) comes by then
START_TIMEOUT_S = 15.0
#: connect's whole budget in the arm process: the ports probed, both interfaces made (up to
#: five tries while the controller frees our last session's registers), the watchdog armed
#: up to three times
CONNECT_TIMEOUT_S = 60.0
#: a call that only reads (a pose, the status) gets this long
READ_TIMEOUT_S = 2.0
#: the state in shared memory older than this: the arm process is not running its turns
STATE_STALE_S = 0.5

#: what runs in the arm process, whatever the kind: the UR driver at the address the kind found
CHILD_DRIVER = "robot_side.arm.ur_rtde:URArm"


class ArmProcess(Arm):
    """A UR driver run in its own process; the same calls as the driver itself.

    ``local`` is the kind's own driver object, built in the node: its config is
    checked when the node is built (before any device moves), it answers the
    preflight, and it finds the controller (a simulator it starts, the lab
    world's), which stays in the node: killing the arm process is then a
    driver's death, not the controller's. It never connects here.
    """

    def __init__(self, local: Any) -> None:
        self.local: Arm = local
        super().__init__(self.local.limits)
        self.config = local.config
        self.simulated = self.local.simulated
        self._child: StdioChild | None = None
        self._state: StateView | None = None
        self._connected = False
        self._died: str | None = None
        self.ready_info: Any = None
        self._last_summary: dict[str, float] = {}

    @property
    def jog_backstop_s(self) -> float:
        return self.local.jog_backstop_s

    # -- the process ---------------------------------------------------------

    def _preflight(self, context: PreflightContext) -> list[Finding]:
        return self.local._preflight(context)

    def _location(self) -> str:
        return self.local._location()

    @property
    def pid(self) -> int | None:
        return None if self._child is None else self._child.pid

    @property
    def is_connected(self) -> bool:
        return self._connected and self._child is not None

    @property
    def needs_reconnect(self) -> bool:
        """The arm process died, stopped writing its state, or its driver asks for one."""
        if not self._connected:
            return False
        if self._child is None or not self._child.running:
            self._noticed_death()
            return True
        state = self._fresh_state()
        if state is None:
            return True
        return bool(state.get("needs_reconnect"))

    def _find_controller(self) -> None:
        """Where the kind's controller is: a simulator started (``OnItsSimulator``), the lab
        world attached (``OnTheWorld``): their ``find_device``."""
        find = getattr(self.local, "find_device", None)
        if find is not None:
            find()

    def _release_controller(self) -> None:
        release = getattr(self.local, "release_device", None)
        if release is not None:
            release()

    def _child_config(self) -> dict[str, Any]:
        """The UR driver's settings from the kind's config (its host now found)."""
        from robot_side.arm.ur_rtde import URArmConfig

        names = {f for f in URArmConfig.__dataclass_fields__}
        return {k: v for k, v in to_dict(self.config).items() if k in names}

    def connect(self) -> None:
        if self.is_connected:
            raise DeviceAlreadyConnectedError(f"{self._what()} is already connected")
        self._find_controller()
        try:
            self._start_process()
        except BaseException:
            self._release_controller()
            raise

    def _start_process(self) -> None:
        path = new_state_file()
        spec = ArmProcessSpec(
            driver=CHILD_DRIVER,
            driver_config=json.dumps(self._child_config()),
            state_file=str(path),
            realtime_priority=int(getattr(self.config, "realtime_priority", 0)),
        )
        child = StdioChild(
            "robot_side.arm.process",
            spec,
            "arm process",
            logging.getLogger().getEffectiveLevel(),
            env=ONE_THREAD_POOLS,  # no BLAS pool thread: child.py says why
        )
        try:
            self.ready_info = child.start_child(START_TIMEOUT_S)
            self._child, self._state = child, StateView(path)
            self._call("connect", timeout_s=CONNECT_TIMEOUT_S)
        except BaseException:
            child.kill()
            self._forget(path)
            raise
        self._connected, self._died = True, None
        log.info("arm process %s: %s connected", child.pid, type(self.local).__name__)

    def disconnect(self) -> None:
        """The arm stopped and its script ended by the arm process, which then exits."""
        child, state = self._child, self._state
        self.keep_alive_summary()  # kept: the node's stats report it after we are gone
        self._connected = False
        if child is None:
            return
        try:
            if child.running:
                self._call("disconnect", timeout_s=CONNECT_TIMEOUT_S)
        except DeviceError as e:
            log.warning("arm process: disconnect failed (%s); ending it", e)
        finally:
            child.stop()  # closes its stdin: it stops the arm again if it must, and exits
            self._forget(None if state is None else Path(state.path))
            self._release_controller()

    def _forget(self, path: Path | None) -> None:
        state, self._child, self._state = self._state, None, None  # readers see None first
        if state is not None:
            state.close()
        if path is not None:
            path.unlink(missing_ok=True)

    def kill(self) -> None:
        """End the arm process at once (tests, the fault matrix): the controller's watchdog
        then stops the arm."""
        if self._child is not None:
            self._child.kill()

    # -- calls ---------------------------------------------------------------

    def _what(self) -> str:
        return f"{type(self.local).__name__} in its arm process"

    def _call(self, method: str, *args: Any, timeout_s: float) -> Any:
        child = self._child
        if child is None or not child.running:
            self._noticed_death()
            raise DeviceNotConnectedError(
                f"{self._what()}: {self._died}; the controller's watchdog stops the arm. The "
                "node's recovery starts a new one"
            )
        try:
            return child.call(method, *args, timeout_s=timeout_s)
        except DeviceTimeoutError as e:
            self._died = f"the arm process did not answer {method} in {timeout_s:g} s"
            child.kill()  # a stuck driver: its watchdog kicks stop, and the controller stops
            press_stop(str(self.config.host), self._died)
            raise DeviceTimeoutError(f"{self._what()}: {self._died}") from e
        except DeviceError as e:
            raise as_driver_error(str(e), method) from None

    def _command_timeout_s(self) -> float:
        return float(getattr(self.config, "command_timeout_s", 2.0)) + 1.0

    def jog(self, velocity: Any, issued_at_s: float | None = None) -> np.ndarray:
        self.require_connected()
        v = self._jog_there(as_vector6(velocity, "jog velocity"), issued_at_s)
        self._last_jog = np.asarray(v, dtype=float)
        self._jog_until = None if not np.any(self._last_jog) else now_s()
        return self._last_jog

    def stop(self) -> None:
        if not self.is_connected:
            return
        self._call("stop_arm", timeout_s=self._command_timeout_s())
        self._jog_until = None
        self._last_jog = np.zeros(6)

    def move_to(self, pose: Any, speed: float | None = None, wait: bool = True) -> None:
        self.require_connected()
        target = as_vector6(pose, "target pose")
        start = self.tcp_pose()
        self._send_move(target, speed)
        if not wait:
            return
        speed = speed or self.limits.default_move_speed_m_s
        distance = max(
            float(np.linalg.norm(target[:3] - start[:3])), turn_angle(start[3:], target[3:])
        )
        accel = self.limits.linear_acceleration_m_s2
        self._wait_move(2 * (distance / speed + speed / accel) + 5.0)

    def _move_finished(self) -> bool:
        return bool(self._call("move_finished", timeout_s=READ_TIMEOUT_S))

    def _wait_move(self, timeout_s: float) -> None:
        deadline = now_s() + timeout_s
        while not self._move_finished():  # each call its own: a stop cuts in between
            if now_s() > deadline:
                self.stop()
                raise DeviceTimeoutError(
                    f"{self._what()}: move did not finish in {timeout_s:.1f} s; the arm was "
                    "told to stop. Check the pendant for a protective stop."
                )
            time.sleep(0.01)

    def tcp_pose(self) -> np.ndarray:
        self.require_connected()
        return np.asarray(self._call("tcp_pose", timeout_s=READ_TIMEOUT_S), dtype=float)

    def joint_positions(self) -> np.ndarray:
        self.require_connected()
        return np.asarray(self._call("joint_positions", timeout_s=READ_TIMEOUT_S), dtype=float)

    # the driver's own primitives are the arm process's: never called here
    def _read_tcp_pose(self) -> np.ndarray:
        return self.tcp_pose()

    def _read_joints(self) -> np.ndarray:
        return self.joint_positions()

    def _send_jog(self, velocity: np.ndarray) -> None:
        self._jog_there(velocity, None)

    def _jog_there(self, velocity: np.ndarray, issued_at_s: float | None) -> Any:
        """The jog, clipped and timed by the arm process's own deadman; what it sent."""
        return self._call("jog", velocity, issued_at_s, timeout_s=self._command_timeout_s())

    def _send_move(self, pose: np.ndarray, speed: float | None) -> None:
        """The move to the arm process (its driver checks and starts it; nothing waits)."""
        self._call("move_to", pose, speed, timeout_s=self._command_timeout_s())

    def _send_stop(self) -> None:
        self.stop()

    # -- what the node reads -------------------------------------------------

    def _noticed_death(self) -> None:
        """The arm process is gone: the controller's watchdog stops the arm; once per death,
        stop is pressed on its dashboard server too (``dashboard_stop``)."""
        if self._died is not None:
            return
        child = self._child
        how = child.how_it_ended() if child is not None else ""
        died = f"the arm process ended ({how})" if how else "the arm process ended"
        if self._connected:
            press_stop(str(self.config.host), died)
        self._died = died

    def _fresh_state(self) -> dict[str, float] | None:
        """The arm process's newest state; None when it stopped writing it."""
        view = self._state  # the recovery's thread may close it and set None meanwhile
        if view is None:
            return None
        state = view.read()
        if not state or now_s() - state["t_write_s"] > STATE_STALE_S:
            return None
        return state

    def live_readings(self) -> dict[str, float]:
        """The newest pose and speed the arm process wrote; never waits on it."""
        return live_of(self._fresh_state())

    def keep_alive_telemetry(self) -> dict[str, float]:
        return keep_alive_of(self._fresh_state())

    def keep_alive_summary(self) -> dict[str, float]:
        """The keep-alive's period (p50, p99, p99.9, max in ms, count) and its scheduling; once
        the arm process has gone, what it last said."""
        state = self._fresh_state()
        if state is not None and state.get("keepalive_count"):
            self._last_summary = {
                k.removeprefix("keepalive_"): v
                for k, v in state.items()
                if k.startswith("keepalive_")
            }
        return dict(self._last_summary)

    def telemetry(self) -> dict[str, float]:
        """What the driver in the arm process last read, from the shared state: never a call
        through the pipe (none waits behind a stop, no round trip at the heartbeat's rate)."""
        self.require_connected()
        state = self._fresh_state()  # one copy: the driver's readings and the pose alike
        return {**self.envelope(), **telemetry_of(state, STATE_STALE_S), **live_of(state)}

    def status(self) -> dict[str, Any]:
        out: dict[str, Any] = {"connected": self.is_connected, "process": self.pid}
        if self.is_connected:
            try:
                out.update(self._call("status", timeout_s=READ_TIMEOUT_S))
            except DeviceError as e:
                out["error"] = str(e)
        out["keep_alive"] = self.keep_alive_summary()
        if self._died:
            out["process_ended"] = self._died
        return out


class InOwnProcess(Device):
    """A kind whose driver runs in an ``ArmProcess`` unless its config says ``own_process =
    false`` (the driver in the node, the old layout). Subclasses name the ``driver`` and its
    ``Config``; what the kind says of itself (family, simulated) is the driver's."""

    driver: ClassVar[type]

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        cls.family = cls.driver.family
        cls.simulated = cls.driver.simulated

    def __new__(cls, config: Any) -> Any:  # type: ignore[misc]
        local = cls.driver(config)
        return ArmProcess(local) if getattr(config, "own_process", False) else local
