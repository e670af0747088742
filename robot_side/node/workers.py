"""The robot's devices off the frame loop: a worker thread and a recovery per device.

The loop posts device calls and never waits on one (device_worker.py); a
device that fails is reconnected in the background (recovery.py) while its
commands are refused. The workers' idle polls read what the heartbeat and
the stimuli carry (the arm's pose and safety state, the grip level), so the
loop reads them without a device call.
"""

from __future__ import annotations

import contextlib
import logging
import threading

from robot_side.arm.base import Arm
from robot_side.devices.device_worker import DeviceRequest, DeviceWorker
from robot_side.devices.recovery import DeviceRecovery
from robot_side.gripper.base import Gripper

log = logging.getLogger(__name__)

#: the least time between two jogs handed to the arm. The controller reads speedL's registers
#: every 2 ms (500 Hz) and an operator jogs at 20 to 60 Hz; in a flood of valid jogs each one
#: was a round trip to the arm process, as fast as it answered, which took the frame loop's
#: CPU. The newest jog waits at most this long and still goes; a stop never waits.
JOG_MIN_GAP_S = 0.004

#: The arm's reconnects back off to at most this: a try while the controller is still away
#: costs one refused TCP connect (URArm checks its ports before ur-rtde's constructors), so
#: a controller that reboots or gets its cable back is used again within about this long.
ARM_RECONNECT_MAX_BACKOFF_S = 2.0
#: the arm telemetry that describes the robot node's own limits, not the controller's state
ARM_ENVELOPE_KEYS = ("arm_ws_", "arm_max_")


class DeviceWorkers:
    """The arm's and the gripper's workers and recoveries; either device may be absent."""

    def __init__(self, arm: Arm | None, gripper: Gripper | None, poll_rate_hz: float) -> None:
        self.arm = arm
        self.gripper = gripper
        self.poll_s = 1.0 / poll_rate_hz
        never = threading.Event()  # replaced in start(); lets stats() work before it
        self.arm_recovery = DeviceRecovery(arm, "arm", never)
        self.gripper_recovery = DeviceRecovery(gripper, "gripper", never)
        #: device calls run on these, never on the frame loop (empty before start())
        self.workers: dict[str, DeviceWorker] = {}
        self.arm_state: dict[str, float] = {}  # the arm worker's latest reading
        self.grip_level: int | None = None  # the gripper worker's latest reading

    def device(self, name: str) -> Arm | Gripper | None:
        return self.arm if name == "arm" else self.gripper if name == "gripper" else None

    def start(self, stack: contextlib.ExitStack) -> None:
        """Recoveries, then a worker per device; on shutdown each finishes with a stop or a hold.

        The recoveries end (``halt``) before the devices close, the workers before them.
        """
        halt = threading.Event()
        self.arm_recovery = DeviceRecovery(
            self.arm, "arm", halt, max_backoff_s=ARM_RECONNECT_MAX_BACKOFF_S
        )
        self.gripper_recovery = DeviceRecovery(self.gripper, "gripper", halt)
        stack.callback(self.arm_recovery.join)
        stack.callback(self.gripper_recovery.join)
        stack.callback(halt.set)
        if self.arm is not None:
            arm = self.workers["arm"] = DeviceWorker(
                "arm",
                self.arm_recovery,
                idle_poll=self._read_arm_state,
                idle_poll_s=self.poll_s,
                paced={"arm_jog": JOG_MIN_GAP_S},
            )
            stack.callback(arm.close, DeviceRequest("arm_stop", self.arm.stop))
        if self.gripper is not None:
            gripper = self.workers["gripper"] = DeviceWorker(
                "gripper",
                self.gripper_recovery,
                idle_poll=self._read_grip_level,
                idle_poll_s=self.poll_s,
            )
            stack.callback(gripper.close)
            gripper.post(DeviceRequest("gripper_activate", self.gripper.activate))

    def post(self, name: str, request: DeviceRequest) -> bool:
        """Hand a call to the device's worker; False when this node has no such device."""
        worker = self.workers.get(name)
        if worker is None:
            return False
        worker.post(request)
        return True

    def stop_devices(self, why: str) -> None:
        """Stop the arm and hold the gripper, through their workers (never waiting here)."""
        if self.arm is not None and self.post("arm", DeviceRequest("arm_stop", self.arm.stop)):
            log.info("arm stopped: %s", why)
        if self.gripper is not None:
            self.post("gripper", DeviceRequest("gripper_hold", self.gripper.hold))

    def _read_arm_state(self) -> None:
        """The arm worker's poll: pose, speed and safety state for the operator's dashboard."""
        telemetry = getattr(self.arm, "telemetry", None)  # a test's stand-in may have none
        self.arm_state = telemetry() if telemetry is not None else {}

    def _read_grip_level(self) -> None:
        """The gripper worker's poll: the stimuli carry the grip level without a device call."""
        self.grip_level = self.gripper.grip_level()

    def stats(self) -> dict[str, float]:
        """Commands the workers applied, refused and superseded; availability; the arm's state."""
        out: dict[str, float] = {}
        for name, worker in self.workers.items():  # counted on the workers' own threads
            c = worker.counters
            out["commands_applied"] = out.get("commands_applied", 0.0) + c["done"]
            out["commands_rejected"] = out.get("commands_rejected", 0.0) + c["failed"]
            out["commands_superseded"] = out.get("commands_superseded", 0.0) + c["superseded"]
            if c["poll_errors"]:
                out[f"{name}_poll_errors"] = float(c["poll_errors"])
        summary = getattr(self.arm, "keep_alive_summary", None)  # a stand-in may have none
        if summary is not None:  # the arm's keep-alive: its period, and whether real-time
            out.update({f"arm_keepalive_{k}": float(v) for k, v in summary().items()})
        return out

    def availability(self) -> dict[str, float]:
        """Each present device's availability and reconnects, and what the arm last said.

        While the arm reconnects what the controller last said is no longer true
        (a speed, a pose): only the envelope is sent.
        """
        out: dict[str, float] = {}
        for name, rec in (("arm", self.arm_recovery), ("gripper", self.gripper_recovery)):
            if rec.device is not None:
                out[f"{name}_available"] = float(rec.available)
                out[f"{name}_reconnects"] = float(rec.recoveries)
        return out

    def arm_readings(self) -> dict[str, float]:
        """What the heartbeat says of the arm: the worker's latest poll, its pose made current.

        The worker's poll waits behind whatever the arm is doing (a stop waits
        for the whole deceleration), so the pose and speed come from the
        driver's own stream where it has one (``Arm.live_readings``: ur-rtde's
        receive cache, no device call): a heartbeat never carries a pose frozen
        behind a stop.
        """
        arm_state = self.arm_state
        if not self.arm_recovery.available:
            return {k: v for k, v in arm_state.items() if k.startswith(ARM_ENVELOPE_KEYS)}
        live = getattr(self.arm, "live_readings", None)  # a test's stand-in may have none
        if live is not None and arm_state:
            try:
                arm_state = {**arm_state, **live()}
            except Exception as e:  # the worker's poll stands; it says what is wrong
                log.debug("arm live readings failed: %s", e)
        return arm_state
