"""Kind "ur_rtde": the UR driver, in its arm process unless ``own_process = false``."""

from __future__ import annotations

from robot_side.arm.process import InOwnProcess
from robot_side.arm.ur_rtde import URArm, URArmConfig


class URArmKind(InOwnProcess):
    """Kind "ur_rtde": ``URArm``, in its arm process unless ``own_process = false``."""

    driver = URArm
    Config = URArmConfig
