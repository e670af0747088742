"""The simulated Robotiq 2F itself: its registers, its fingers and the object between them.

``GripperModel`` is the gripper: activation sequence, fingers moving at a
finite speed toward the requested position, an object between the fingers
that stops them (or, if soft, gives way in proportion to the force
setting), faults. The socket server (``robot_side.gripper.sim``) and the
Modbus RTU one (``robot_side.gripper.rtu_sim``) serve it.

Object model: the object's faces meet the fingers at ``contact_position``
counts. Closing past it, the fingers squeeze in by up to
``compression_at_full_force * FOR / 255`` counts (0 = rigid). If the
requested position lies deeper, the fingers stop there and report OBJ=2
(stopped on an object while closing); otherwise they reach the request and
report OBJ=3, as a real 2F does on a soft object. OBJ=1 (contact while
opening, an internal grip) is not modelled.

A physics world can take the fingers over (``GripperModel.fingers``, a
``FingerDrive``): the model then ramps the commanded position at the set
speed, hands it and the force setting to the world, and reads back where the
fingers really are; an object is detected when they stall against something.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass
from typing import Protocol

from common.clocks.clock import Rate, now_s
from common.config.typed import param
from common.errors import ConfigError
from robot_side.gripper.base import ActivationStatus, ObjectStatus

log = logging.getLogger(__name__)


FAULT_NOT_ACTIVATED = 0x07
#: counts between commanded and actual finger position that still count as "there"
AT_POSITION_TOLERANCE = 2.0


class FingerDrive(Protocol):
    """Fingers that a world moves: the model commands them and reads them back."""

    def command(self, position_counts: float, force_setting: int) -> None:
        """Servo the fingers toward ``position_counts`` pushing no harder than ``force_setting``."""

    def position_counts(self) -> float:
        """Where the fingers are, in Robotiq counts."""

    def stalled_on_object(self) -> bool:
        """The fingers have stopped against an object between them."""


@dataclass
class GripperModelConfig:
    activation_time_s: float = param(0.3, "STA 1 -> 3 (a real 2F-85 takes about 1.5 s)")
    min_speed_counts_s: float = param(60.0, "finger speed at SPE 0 (2F-85: 20 mm/s)")
    max_speed_counts_s: float = param(450.0, "finger speed at SPE 255 (2F-85: 150 mm/s)")
    stroke_end_position: int = param(255, "where the fingers stop when closed on nothing")
    object_present: bool = param(True, "an object (the pipette) sits between the fingers")
    contact_position: int = param(196, "counts at which closing fingers touch the object")
    compression_at_full_force: float = param(
        60.0, "counts the object gives way at FOR 255 (0 = rigid); a pipette is soft"
    )
    tick_hz: float = param(200.0, "model update rate")

    def __post_init__(self) -> None:
        if not 0 < self.min_speed_counts_s <= self.max_speed_counts_s:
            raise ConfigError("gripper sim: need 0 < min_speed_counts_s <= max_speed_counts_s")
        if not 0 <= self.contact_position <= 255 or not 0 <= self.stroke_end_position <= 255:
            raise ConfigError("gripper sim: positions must be in 0..255")
        if self.compression_at_full_force < 0 or self.activation_time_s < 0:
            raise ConfigError("gripper sim: compression and activation time must be >= 0")


class GripperModel:
    """The gripper's registers and fingers; thread-safe, advanced by ``step``."""

    def __init__(self, config: GripperModelConfig | None = None) -> None:
        self.config = config or GripperModelConfig()
        self.lock = threading.RLock()
        self.act = 0
        self.gto = 0
        self.atr = 0
        self.pr = 0  # requested position (rPR)
        self.spe = 255
        self.force = 150
        self.pos = 0.0  # finger position, counts
        self.sta = ActivationStatus.RESET
        self.obj = ObjectStatus.MOVING
        self.flt = 0
        self._activation_done_at: float | None = None
        self._activation_fault = 0
        self._moving = False
        #: a world's fingers, when one drives them (None: the built-in object model)
        self.fingers: FingerDrive | None = None
        self._commanded = 0.0

    # -- register writes ------------------------------------------------------

    def write(self, **values: int) -> None:
        """Apply robot-side registers (ACT, GTO, ATR, POS, SPE, FOR) as one write."""
        with self.lock:
            for k, v in values.items():
                v = max(0, min(255, int(v)))
                if k == "ACT":
                    self._set_act(v)
                elif k == "GTO":
                    self.gto = 1 if v else 0
                elif k == "ATR":
                    self.atr = 1 if v else 0
                elif k == "POS":
                    self.pr = v
                elif k == "SPE":
                    self.spe = v
                elif k == "FOR":
                    self.force = v
                else:
                    raise KeyError(k)
            if self.gto and self.act == 0:
                self.flt = FAULT_NOT_ACTIVATED
            elif self.gto and self.sta == ActivationStatus.ACTIVE:
                if self.flt == FAULT_NOT_ACTIVATED:
                    self.flt = 0
                self._moving = True
                self.obj = ObjectStatus.MOVING

    def _set_act(self, v: int) -> None:
        if v and not self.act:
            self.sta = ActivationStatus.ACTIVATING
            self._activation_done_at = now_s() + self.config.activation_time_s
            self.flt = 0
        elif not v:
            self.sta = ActivationStatus.RESET
            self._activation_done_at = None
            self.gto = 0
            self.obj = ObjectStatus.MOVING
            self._moving = False
        self.act = 1 if v else 0

    def fail_next_activation(self, code: int = 0x0D) -> None:
        """The next activation ends in fault ``code`` (0x0D: something blocks the fingers)."""
        with self.lock:
            self._activation_fault = code

    def inject_fault(self, code: int) -> None:
        """A fault as the gripper reports it; 0x0A and up also stop the fingers."""
        with self.lock:
            self.flt = code
            if code >= 0x0A:
                self._moving = False

    def set_object(
        self,
        present: bool,
        contact_position: int | None = None,
        compression_at_full_force: float | None = None,
    ) -> None:
        with self.lock:
            self.config.object_present = present
            if contact_position is not None:
                self.config.contact_position = contact_position
            if compression_at_full_force is not None:
                self.config.compression_at_full_force = compression_at_full_force

    # -- register reads -------------------------------------------------------

    def read(self) -> dict[str, int]:
        with self.lock:
            return {
                "ACT": self.act,
                "GTO": self.gto,
                "ATR": self.atr,
                "STA": int(self.sta),
                "OBJ": int(self.obj),
                "FLT": self.flt,
                "PRE": self.pr,
                "POS": round(self.pos),
                "SPE": self.spe,
                "FOR": self.force,
                "CUR": self._current(),
            }

    def _current(self) -> int:
        """gCU, in 10 mA steps: more while squeezing, a little while moving."""
        if self.obj == ObjectStatus.CONTACT_CLOSING:
            return 10 + self.force // 4
        return 5 if self._moving else 0

    # -- physics ----------------------------------------------------------------

    def run(self, quit_event: threading.Event) -> None:
        """Step at ``tick_hz`` by the time that really passed, until ``quit_event``."""
        rate = Rate(self.config.tick_hz)
        last = now_s()
        while not quit_event.is_set():
            t = now_s()
            dt, last = min(t - last, 0.05), t
            if dt > 0:
                self.step(dt)
            rate.sleep()

    def step(self, dt: float) -> None:
        with self.lock:
            if self.fingers is not None and self.sta != ActivationStatus.ACTIVATING:
                self._step_driven(self.fingers, dt)
                return
            if self.sta == ActivationStatus.ACTIVATING:
                if self.fingers is not None:  # activation opens the fingers fully
                    self._commanded = 0.0
                    self.fingers.command(0.0, 255)
                # activation opens the fingers fully
                self.pos = max(0.0, self.pos - self.config.max_speed_counts_s * dt)
                if self._activation_done_at is not None and now_s() >= self._activation_done_at:
                    if self._activation_fault:
                        self.flt, self._activation_fault = self._activation_fault, 0
                        self.sta = ActivationStatus.RESET
                        self._activation_done_at = None
                        return
                    self.pos = 0.0
                    self.sta = ActivationStatus.ACTIVE
                    self.obj = ObjectStatus.AT_POSITION
                    self._activation_done_at = None
                return
            if not self._moving or self.sta != ActivationStatus.ACTIVE or self.flt >= 0x0A:
                return
            c = self.config
            speed = c.min_speed_counts_s + (c.max_speed_counts_s - c.min_speed_counts_s) * (
                self.spe / 255
            )
            target = float(min(self.pr, c.stroke_end_position))
            limit = None
            closing = target > self.pos
            if closing and c.object_present:
                limit = c.contact_position + c.compression_at_full_force * self.force / 255
            new = (
                min(target, self.pos + speed * dt)
                if closing
                else max(target, self.pos - speed * dt)
            )
            if limit is not None and target > limit and new >= limit:
                self.pos = max(self.pos, limit)
                self._moving = False
                self.obj = ObjectStatus.CONTACT_CLOSING
                return
            self.pos = new
            if self.pos == target:
                self._moving = False
                self.obj = ObjectStatus.AT_POSITION

    def _step_driven(self, fingers: FingerDrive, dt: float) -> None:
        """The world moves the fingers: ramp the command, read the position, detect objects."""
        self.pos = min(255.0, max(0.0, fingers.position_counts()))
        if not self._moving or self.sta != ActivationStatus.ACTIVE or self.flt >= 0x0A:
            return
        c = self.config
        speed = c.min_speed_counts_s + (c.max_speed_counts_s - c.min_speed_counts_s) * (
            self.spe / 255
        )
        target = float(min(self.pr, c.stroke_end_position))
        error = target - self._commanded
        self._commanded += max(-speed * dt, min(speed * dt, error))
        fingers.command(self._commanded, self.force)
        if abs(self.pos - target) <= AT_POSITION_TOLERANCE:
            self._moving = False
            self.obj = ObjectStatus.AT_POSITION
        elif self._commanded == target and target > self.pos and fingers.stalled_on_object():
            self._moving = False
            self.obj = ObjectStatus.CONTACT_CLOSING
