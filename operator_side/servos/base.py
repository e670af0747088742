"""The servo bus interface: goal positions in counts, one sync write per cycle.

Angles are converted to counts (and clipped to each servo's limits) by
``operator_side.servos.calibration`` before they reach a bus; a bus refuses
counts outside those limits as a second line of defence.
"""

from __future__ import annotations

import abc
from collections.abc import Mapping

from common.devices import Device


class ServoBus(Device):
    family = "servo bus"

    @abc.abstractmethod
    def write_goals(self, goals: Mapping[int, int]) -> None:
        """Send all goal positions (servo id -> counts) in one sync write."""

    @abc.abstractmethod
    def read_positions(self) -> dict[int, int]:
        """Present positions (servo id -> counts), for monitoring."""

    @abc.abstractmethod
    def set_torque(self, enabled: bool) -> None:
        """Torque on or off for every servo on the bus."""
