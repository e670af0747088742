"""Every registered kind describes itself: simulated or not, and what is wrong before connect."""

from __future__ import annotations

import importlib

import pytest

from common.devices.lifecycle import Device, load_object
from common.devices.preflight import FAIL, PreflightContext

FAMILIES = (
    "robot_side.tactile",
    "robot_side.gripper",
    "robot_side.arm",
    "robot_side.camera",
    "operator_side.servos",
)
#: what a kind's config must name to build at all (the lab camera: the world it asks)
REQUIRED = {("robot_side.camera", "lab"): {"addresses_file": "world.json"}}
ALL_KINDS = [
    (family, kind, target)
    for family in FAMILIES
    for kind, target in importlib.import_module(family).KINDS.items()
]


@pytest.mark.parametrize(("family", "kind", "target"), ALL_KINDS)
def test_every_kind_is_a_device_that_says_whether_it_is_simulated(family, kind, target):
    cls = load_object(target)
    assert issubclass(cls, Device)
    assert isinstance(cls.simulated, bool)


@pytest.mark.parametrize(
    ("family", "kind", "target"),
    [k for k in ALL_KINDS if load_object(k[2]).simulated],
)
def test_simulated_kinds_have_nothing_to_look_for(family, kind, target):
    cls = load_object(target)
    device = cls(cls.Config(**REQUIRED.get((family, kind), {})))
    assert device.preflight(PreflightContext(where=family)) == []
    assert device.location() == ""


@pytest.mark.parametrize(
    ("family", "kind"),
    [
        ("robot_side.tactile", "serial"),
        ("robot_side.gripper", "robotiq_rtu"),
        ("operator_side.servos", "feetech"),
    ],
)
def test_a_serial_kind_names_its_missing_port_and_the_config_key(tmp_path, family, kind):
    cls = load_object(importlib.import_module(family).KINDS[kind])
    config = cls.Config(port=str(tmp_path / "ttyUSB9"))
    findings = cls(config).preflight(PreflightContext(where="robot.x"))
    assert [f.status for f in findings] == [FAIL]
    assert "does not exist" in findings[0].detail and "robot.x.port" in findings[0].fix


def test_the_arm_names_its_pendant_and_the_gripper_its_urcap():
    from tests_support import free_ports

    from robot_side.arm.ur_rtde import URArm, URArmConfig
    from robot_side.gripper.urcap_socket import RobotiqSocketConfig, RobotiqSocketGripper

    (port,) = free_ports(1)
    context = PreflightContext(where="robot.arm", tcp_timeout_s=0.5)
    (arm,) = URArm(URArmConfig(host="127.0.0.1")).preflight(context)
    assert arm.status == FAIL and "Remote Control" in arm.fix and "29999" in arm.detail
    gripper = RobotiqSocketGripper(RobotiqSocketConfig(host="127.0.0.1", port=port))
    (finding,) = gripper.preflight(context)
    assert "URCap" in finding.fix and f"127.0.0.1:{port} refused" in finding.detail
