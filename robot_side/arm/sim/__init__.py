"""A UR e-Series controller simulator that the real ur-rtde clients talk to.

``URSimulator`` serves RTDE, the dashboard and the script port on a loopback
address with a kinematic UR3e behind them; ``URSimProcess`` runs it in a
child process (required next to ur-rtde, whose constructors hold the GIL);
``SimulatedArm`` is the kind "simulated": the real ``URArm`` driver
connected to a simulator it starts itself, so node code is the same as on
the robot. ``python -m robot_side.arm.sim`` serves one from a shell.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from common.config.typed import param
from common.devices.lifecycle import OnItsSimulator
from robot_side.arm.process import InOwnProcess
from robot_side.arm.sim.process import URSimProcess
from robot_side.arm.sim.server import URSimConfig, URSimulator
from robot_side.arm.ur_rtde import URArm, URArmConfig

__all__ = ["SimulatedArm", "SimulatedArmConfig", "URSimConfig", "URSimProcess", "URSimulator"]

log = logging.getLogger(__name__)


@dataclass
class SimulatedArmConfig(URArmConfig):
    host: str = param("auto", "ignored: the simulator's address is used (sim.host picks it)")
    sim: URSimConfig = param(URSimConfig(), "the simulated controller")


class SimulatedArm(OnItsSimulator, URArm):
    """The real URArm driver against a simulator it starts on connect and stops on disconnect."""

    Config = SimulatedArmConfig

    def __init__(self, config: SimulatedArmConfig | None = None) -> None:
        super().__init__(config or SimulatedArmConfig())
        self.sim: URSimProcess | None = None

    def _start_simulator(self) -> None:
        assert isinstance(self.config, SimulatedArmConfig)
        if self.sim is None or not self.sim.running:
            self.sim = URSimProcess(self.config.sim).start()
        assert self.sim.host is not None
        self.config.host = self.sim.host

    def _stop_simulator(self) -> None:
        if self.sim is not None:
            self.sim.stop()
            self.sim = None


class SimulatedArmKind(InOwnProcess):
    """Kind "simulated": the simulator in the node, ``URArm`` in its arm process unless
    ``own_process = false``."""

    driver = SimulatedArm
    Config = SimulatedArmConfig
