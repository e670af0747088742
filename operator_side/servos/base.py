"""The servo bus interface: goal positions in counts, one sync write per cycle.

Angles are converted to counts (and clipped to each servo's limits) by
``operator_side.servos.calibration`` before they reach a bus; a bus refuses
counts outside those limits as a second line of defence. That check lives
here, in ``write_goals``, so no bus can forget it: a bus only implements
``_write_goals`` for goals that have passed it.
"""

from __future__ import annotations

import abc
import time
from collections.abc import Mapping

from common.devices.lifecycle import Device
from common.errors import DeviceError
from operator_side.servos.calibration import LinkGlideCalibration
from operator_side.servos.limits import GoalOutOfLimitsError, check_goals

#: a servo this close to its goal (counts, about 1.4 degrees) has arrived
ARRIVED_COUNTS = 16
_ARRIVAL_READ_S = 0.01


class ServoBus(Device):
    family = "servo bus"

    #: The limits this bus enforces (None until ``connect`` loads them); the node renders with them.
    calibration: LinkGlideCalibration | None = None
    #: Writes refused by the limits check (nothing was sent for them).
    refused_writes: int = 0

    def write_goals(self, goals: Mapping[int, int]) -> dict[int, int]:
        """Send all goal positions (servo id -> counts) in one sync write; returns what was sent.

        Out-of-limit goals raise ``GoalOutOfLimitsError`` and nothing is sent.
        """
        self.require_connected()
        calibration = self.calibration
        if calibration is None:
            raise DeviceError(
                f"servo bus {type(self).__name__} has no calibration: connect() loads it"
            )
        try:
            checked = check_goals(calibration, goals)
        except GoalOutOfLimitsError:
            self.refused_writes += 1
            raise
        self._write_goals(checked)
        return checked

    @abc.abstractmethod
    def _write_goals(self, goals: dict[int, int]) -> None:
        """Put goals already checked against the calibration on the wire."""

    @abc.abstractmethod
    def read_positions(self) -> dict[int, int]:
        """Present positions (servo id -> counts), for monitoring."""

    @abc.abstractmethod
    def set_torque(self, enabled: bool) -> None:
        """Torque on or off for every servo on the bus."""

    def wait_for_arrival(self, goals: Mapping[int, int], within_s: float) -> dict[int, int]:
        """Read positions until every servo is within ``ARRIVED_COUNTS`` of its goal, at most
        ``within_s``; returns the servos still away (id -> counts), empty once all arrived.

        A lift waits for it before torque goes off: a linkage let go mid-way stays there.
        """
        deadline = time.monotonic() + within_s
        while True:
            present = self.read_positions()
            away = {i: present[i] for i in goals if abs(present[i] - goals[i]) > ARRIVED_COUNTS}
            if not away or time.monotonic() >= deadline:
                return away
            time.sleep(_ARRIVAL_READ_S)
