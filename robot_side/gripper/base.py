"""The gripper interface every Robotiq 2F driver and simulator implements.

Positions are Robotiq counts: 0 fully open .. 255 fully closed (the 2F-85
stops at about 230 when closed on nothing). Speed and force are 0..255 too.
All clamping happens here, before a driver sees a value, so a new driver
cannot forget it.

Grip levels are the paper's 31 gripper positions "from minimum pressure
applied to the pipette to maximum": level 1 is the position where the
fingertip pads first register the pipette, level 31 the strongest squeeze
the lab allows. Both ends are site settings (``GripLevels``), because they
depend on the pipette, the pad thickness and the finger model.
"""

from __future__ import annotations

import abc
import logging
import math
import numbers
import time
from dataclasses import dataclass
from enum import IntEnum
from typing import Any

from common.clocks.clock import now_s
from common.config.typed import param
from common.devices.lifecycle import Device
from common.errors import ConfigError, DeviceError, DeviceTimeoutError
from common.tactile.contract import N_GRIP_LEVELS

log = logging.getLogger(__name__)

POSITION_OPEN = 0
POSITION_MAX = 255


class ObjectStatus(IntEnum):
    """Robotiq gOBJ: why the fingers stopped (or that they still move)."""

    MOVING = 0  # fingers moving toward the requested position
    CONTACT_OPENING = 1  # stopped on an object while opening
    CONTACT_CLOSING = 2  # stopped on an object while closing (a grasp)
    AT_POSITION = 3  # reached the requested position: no object stopped it


class ActivationStatus(IntEnum):
    """Robotiq gSTA."""

    RESET = 0  # reset or automatic release
    ACTIVATING = 1
    # 2 is unused by the gripper
    ACTIVE = 3


class GripperFaultError(DeviceError):
    """The gripper reports a fault (gFLT != 0); the message says what to do."""


#: gFLT codes the 2F manual documents, with the action a user can take.
FAULTS: dict[int, str] = {
    0x05: "action delayed: activation (re-activation) must complete first",
    0x07: "activation bit must be set before moving: call activate()",
    0x08: "maximum operating temperature exceeded: let the gripper cool down",
    0x09: "no communication for at least 1 s: check the cable or the URCap",
    0x0A: "under minimum operating voltage: check the 24 V supply",
    0x0B: "automatic release in progress",
    0x0C: "internal fault: contact Robotiq support",
    0x0D: "activation fault: check that nothing blocks the fingers, then re-activate",
    0x0E: "overcurrent: check that nothing blocks the fingers, then re-activate",
    0x0F: "automatic release completed: re-activate",
}


def fault_text(code: int) -> str:
    return FAULTS.get(code, f"unknown fault 0x{code:02X}: see the Robotiq 2F manual")


@dataclass
class GripLevels:
    """Level n of 31 -> (position, force): linear between the two ends.

    Levels are positions because the paper defines them so (its tactile data
    are labelled by gripper position), and each level must be its own
    position so ``grip_level()`` can be read back from the fingers: hence at
    least 30 counts between the ends. Force rises with the level too: the
    Robotiq stops and reports a grasp (OBJ=2) when the squeeze needs more
    than the force setting, so a light level never crushes a pipette that is
    stiffer than expected.
    """

    level1_position: int = param(
        200, "counts where the pads first register the pipette (measure on site)"
    )
    level31_position: int = param(230, "counts for the strongest squeeze the lab allows")
    level1_force: int = param(20, "force setting (0..255) at the lightest level")
    level31_force: int = param(150, "force setting (0..255) at the strongest level")
    speed: int = param(128, "closing speed (0..255) for grip levels: half speed, gentle contact")
    open_margin: int = param(
        5, "counts more open than level 1 that still read as level 1 (else: open, None)"
    )
    ease_counts: int = param(
        15,
        "an ease opens this many counts past open_margin below level 1: the pads clear the "
        "pipette (2.5 mm a finger on a 2F-85) and a re-grasp closes in about 0.15 s, not 0.8",
    )

    def __post_init__(self) -> None:
        for name in ("level1_position", "level31_position"):
            if not 0 <= getattr(self, name) <= POSITION_MAX:
                raise ConfigError(f"grip levels: {name} must be in 0..255")
        for name in ("level1_force", "level31_force", "speed"):
            if not 0 <= getattr(self, name) <= 255:
                raise ConfigError(f"grip levels: {name} must be in 0..255")
        if self.level31_position - self.level1_position < N_GRIP_LEVELS - 1:
            raise ConfigError(
                "grip levels: level31_position must be at least 30 counts more closed than "
                "level1_position, so each of the 31 levels is its own position"
            )
        if self.open_margin < 0:
            raise ConfigError("grip levels: open_margin must not be negative")
        if self.ease_counts < 1:
            raise ConfigError("grip levels: ease_counts must be at least 1 (else it holds)")

    def position(self, level: int) -> int:
        span = self.level31_position - self.level1_position
        return self.level1_position + round(span * (level - 1) / (N_GRIP_LEVELS - 1))

    def force(self, level: int) -> int:
        span = self.level31_force - self.level1_force
        return self.level1_force + round(span * (level - 1) / (N_GRIP_LEVELS - 1))

    def ease_position(self) -> int:
        """Where an ease opens to: just more open than any level reads (``level_at``: None)."""
        return max(POSITION_OPEN, self.level1_position - self.open_margin - self.ease_counts)

    def level_at(self, position: int) -> int | None:
        """The level nearest ``position``; None when more open than level 1 allows."""
        if position < self.level1_position - self.open_margin:
            return None
        span = self.level31_position - self.level1_position
        level = 1 + round((position - self.level1_position) * (N_GRIP_LEVELS - 1) / span)
        return min(N_GRIP_LEVELS, max(1, level))


def _clamp_byte(name: str, value: float) -> int:
    """0..255 with a warning when clamped; NaN, bools and non-numbers are refused."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        raise ValueError(f"gripper {name} must be a number in 0..255, not {value!r}")
    clamped = min(255, max(0, round(float(value))))
    if clamped != value:
        log.warning("gripper %s %r clamped to %d", name, value, clamped)
    return clamped


@dataclass(frozen=True, slots=True)
class GripperState:
    """One read of the gripper's status registers."""

    activation: int  # gSTA
    goto: bool  # gGTO
    object_status: int  # gOBJ
    fault: int  # gFLT
    requested_position: int  # gPR echo
    position: int  # gPO


class Gripper(Device):
    """Robotiq 2F: activation, non-blocking moves, grip levels, object detection.

    Subclasses implement the wire: ``_write_command`` and ``_read_state``
    (and ``_write_activate``). Everything a caller can get wrong is checked
    here first.
    """

    family = "gripper"

    def __init__(self, levels: GripLevels | None = None, activation_timeout_s: float = 5.0):
        self.levels = levels or GripLevels()
        self.activation_timeout_s = activation_timeout_s
        self._last_speed = self.levels.speed
        self._last_force = self.levels.level31_force

    # -- what drivers implement -------------------------------------------

    @abc.abstractmethod
    def _write_activate(self) -> None:
        """Start the activation sequence (rACT 0 -> 1); does not wait."""

    @abc.abstractmethod
    def _write_command(self, position: int, speed: int, force: int, go: bool) -> None:
        """Send POS/SPE/FOR and set GTO; values are already clamped."""

    @abc.abstractmethod
    def _read_state(self) -> GripperState:
        """Read STA, GTO, OBJ, FLT, PRE and POS."""

    # -- public API --------------------------------------------------------

    def state(self) -> GripperState:
        self.require_connected()
        return self._read_state()

    def activate(self, wait: bool = True) -> None:
        """Activate (the fingers open and close once to find their stroke).

        An already active gripper is left alone: re-activating moves the
        fingers, which would drop whatever they hold.
        """
        self.require_connected()
        if self._read_state().activation == ActivationStatus.ACTIVE:
            return
        self._write_activate()
        if not wait:
            return
        deadline = now_s() + self.activation_timeout_s
        while True:
            st = self._read_state()
            if st.activation == ActivationStatus.ACTIVE:
                log.info("%s activated", type(self).__name__)
                return
            if st.fault not in (0, 0x05):
                raise GripperFaultError(f"gripper activation failed: {fault_text(st.fault)}")
            if now_s() > deadline:
                raise DeviceTimeoutError(
                    f"gripper did not finish activating in {self.activation_timeout_s:.1f} s "
                    f"(STA={st.activation}); check that nothing blocks the fingers"
                )
            time.sleep(0.02)

    def is_active(self) -> bool:
        return self.state().activation == ActivationStatus.ACTIVE

    def move(self, position: int, speed: int = 255, force: int = 150) -> None:
        """Send the fingers toward ``position`` (0 open .. 255 closed); returns at once."""
        self.require_connected()
        position = _clamp_byte("position", position)
        speed = _clamp_byte("speed", speed)
        force = _clamp_byte("force", force)
        self._write_command(position, speed, force, go=True)
        self._last_speed, self._last_force = speed, force

    def open(self, speed: int = 255, force: int = 150) -> None:
        self.move(POSITION_OPEN, speed, force)

    def ease(self, speed: int = 255, force: int = 150) -> None:
        """Open just enough to let go (``GripLevels.ease_position``), never closing further.

        A re-grasp (the assist's) then closes a few counts instead of the whole stroke.
        Fingers already more open than that stop where they are.
        """
        self.require_connected()
        here = self._read_state().position
        self.move(min(here, self.levels.ease_position()), speed, force)

    def close_to_level(self, level: int) -> None:
        """Close to grip level 1..31 (lightest touch .. strongest squeeze)."""
        if isinstance(level, bool) or not isinstance(level, int):
            raise ValueError(f"grip level must be an integer 1..{N_GRIP_LEVELS}, not {level!r}")
        if not 1 <= level <= N_GRIP_LEVELS:
            raise ValueError(f"grip level {level} is not in 1..{N_GRIP_LEVELS}")
        self.move(self.levels.position(level), self.levels.speed, self.levels.force(level))

    def hold(self) -> None:
        """Stop the fingers where they are now (the requested position becomes the present one).

        Speed and force stay as last commanded, so a held pipette is squeezed no harder.
        """
        self.require_connected()
        st = self._read_state()
        self._write_command(st.position, self._last_speed, self._last_force, go=True)

    def position(self) -> int:
        return self.state().position

    def object_detected(self) -> bool:
        """True when the fingers stopped on something (OBJ 1 or 2).

        A soft pipette squeezed all the way to a level's position reads
        OBJ=3 (at position) on a real 2F; the tactile pads are the better
        judge of "holding something" in that case.
        """
        return self.state().object_status in (
            ObjectStatus.CONTACT_OPENING,
            ObjectStatus.CONTACT_CLOSING,
        )

    def grip_level(self) -> int | None:
        """The level nearest the present finger position; None when open or closed on nothing."""
        return self._level_from(self.state())

    def _level_from(self, st: GripperState) -> int | None:
        if st.activation != ActivationStatus.ACTIVE:
            return None
        if (
            st.object_status == ObjectStatus.AT_POSITION
            and st.position > self.levels.level31_position + self.levels.open_margin
        ):
            return None  # closed past the strongest level: nothing between the fingers
        return self.levels.level_at(st.position)

    def fault(self) -> int:
        return self.state().fault

    def status(self) -> dict[str, Any]:
        out = super().status()
        if not self.is_connected:
            return out
        try:
            st = self._read_state()
        except DeviceError as e:
            out["error"] = str(e)
            return out
        out.update(
            activation=st.activation,
            position=st.position,
            requested_position=st.requested_position,
            object_status=st.object_status,
            object_detected=st.object_status in (1, 2),
            grip_level=self._level_from(st),
            fault=st.fault,
        )
        if st.fault:
            out["fault_text"] = fault_text(st.fault)
        return out
