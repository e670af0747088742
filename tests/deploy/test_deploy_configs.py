"""The shipped scenes and the example configs load, build their devices, and document every key."""

from __future__ import annotations

import dataclasses
import importlib
import re
import subprocess
from importlib import resources
from typing import Any

import pytest
from deploy_support import ENV, EXAMPLES, cli

from common.config.typed import load_toml
from common.devices.lifecycle import build_device, load_object
from deploy.scene import load_scene
from operator_side.node.config import OperatorConfig
from robot_side.node.config import RobotConfig

SCENES = sorted(
    p.name[:-5] for p in resources.files("deploy.scenes").iterdir() if p.name.endswith(".toml")
)
FAMILIES = {
    "robot": {
        "tactile": "robot_side.tactile",
        "gripper": "robot_side.gripper",
        "arm": "robot_side.arm",
    },
    "operator": {"servos": "operator_side.servos"},
}
#: Keys an example config may leave out, and why.
NOT_LISTED = {
    # The inline calibration is replaced by calibration_file (written by `deepxpalm calibrate`).
    "operator.servos.calibration",
}


def _registry(module: str) -> dict[str, str]:
    import importlib

    return importlib.import_module(module).KINDS


def test_the_scenes_the_deploy_issue_names_are_shipped():
    assert {"demo", "covid_lab", "operator_station", "netsim"} <= set(SCENES)


@pytest.mark.parametrize("name", SCENES)
def test_every_shipped_scene_loads_and_its_devices_build(name):
    scene = load_scene(name)
    assert scene.scene.name == name
    for role, families in FAMILIES.items():
        node = getattr(scene, role)
        for family, module in families.items():
            section = getattr(node, family)
            if section.get("kind", "none") == "none":
                continue
            # Builds the kind's typed config (names every unknown key); no I/O before connect().
            device = build_device(_registry(module), section, f"{role}.{family}")
            assert not device.is_connected


def test_full_hardware_scene_uses_real_drivers_and_curve():
    scene = load_scene("covid_lab")
    assert scene.robot.tactile["kind"] == "serial"
    assert scene.robot.gripper["kind"] == "robotiq_socket"
    assert scene.robot.arm["kind"] == "ur_rtde"
    assert scene.operator.servos["kind"] == "feetech"
    assert scene.robot.link.security.mode == scene.operator.link.security.mode == "curve"
    assert not scene.network.enabled


def test_netsim_scene_simulates_every_device_and_names_a_real_scenario():
    from common.netsim.scenario import load_scenario

    scene = load_scene("netsim")
    sections = {
        "robot_side.tactile": scene.robot.tactile,
        "robot_side.gripper": scene.robot.gripper,
        "robot_side.arm": scene.robot.arm,
        "operator_side.servos": scene.operator.servos,
    }
    for family, section in sections.items():
        kind = importlib.import_module(family).KINDS[section["kind"]]
        assert load_object(kind).simulated, f"{family} kind {section['kind']!r} is real hardware"
    assert scene.network.enabled
    load_scenario(scene.network.scenario)
    text = resources.files("deploy.scenes").joinpath("netsim.toml").read_text()
    shipped = {
        p.name[:-5]
        for p in resources.files("common.netsim.scenarios").iterdir()
        if p.name.endswith(".toml")
    }
    documented = set(re.findall(r"^#   (\w+)\s{2,}", text, re.M))
    assert documented == shipped, "netsim.toml should describe every shipped scenario"


@pytest.mark.slow
@pytest.mark.parametrize("role", ["robot", "operator"])
def test_example_config_prints_through_the_node_cli(role):
    out = subprocess.run(
        cli(role, "--config", str(EXAMPLES / f"{role}.toml"), "--print-config"),
        capture_output=True,
        text=True,
        timeout=60,
        env=ENV,
    )
    assert out.returncode == 0, out.stderr
    assert 'mode = "curve"' in out.stdout
    assert "/etc/deepxpalm/keys/" in out.stdout


def _expected_keys(obj: Any, table: str, out: set[str]) -> None:
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        key = f"{table}.{f.name}"
        if dataclasses.is_dataclass(value):
            _expected_keys(value, key, out)
        else:
            out.add(key)


def _listed_keys(text: str) -> set[str]:
    """table.key for every `key = ...` line, commented out or not."""
    table = ""
    out = set()
    for line in text.splitlines():
        header = re.match(r"^\s*\[([\w.]+)\]", line)
        if header:
            table = header.group(1)
            continue
        m = re.match(r"^\s*#?\s*(\w+)\s*=", line)
        if m and table:
            out.add(f"{table}.{m.group(1)}")
    return out


@pytest.mark.parametrize("role", ["robot", "operator"])
def test_example_config_lists_every_setting_with_a_comment(role):
    path = EXAMPLES / f"{role}.toml"
    text = path.read_text()
    data = load_toml(path)[role]
    cls = RobotConfig if role == "robot" else OperatorConfig
    expected: set[str] = set()
    defaults = cls()
    for f in dataclasses.fields(defaults):
        value = getattr(defaults, f.name)
        key = f"{role}.{f.name}"
        if f.name in FAMILIES[role]:
            section = data[f.name]
            expected.add(f"{key}.kind")
            config_cls = load_object(_registry(FAMILIES[role][f.name])[section["kind"]]).Config
            _expected_keys(config_cls(), key, expected)
        elif dataclasses.is_dataclass(value):
            _expected_keys(value, key, expected)
        else:
            expected.add(key)
    expected = {k for k in expected if not any(k.startswith(n) for n in NOT_LISTED)}
    missing = expected - _listed_keys(text)
    assert not missing, f"{path.name} does not mention {sorted(missing)}"
    # Each setting has a comment on its line or in the paragraph it belongs to.
    lines = text.splitlines()
    for i, line in enumerate(lines):
        if re.match(r"^\w+\s*=", line) and "#" not in line:
            j = i - 1
            while j >= 0 and lines[j].strip() and not lines[j].startswith("["):
                if lines[j].lstrip().startswith("#"):
                    break
                j -= 1
            else:
                j = -1
            assert j >= 0 and lines[j].lstrip().startswith("#"), f"uncommented: {line!r}"


def test_example_configs_name_stable_device_paths_and_the_ur():
    robot = load_toml(EXAMPLES / "robot.toml")["robot"]
    operator = load_toml(EXAMPLES / "operator.toml")["operator"]
    assert robot["tactile"]["port"] == "/dev/deepxpalm-tactile"
    assert operator["servos"]["port"] == "/dev/deepxpalm-servos"
    assert robot["gripper"]["port"] == 63352
    assert robot["gripper"]["host"] == robot["arm"]["host"]
    assert robot["link"]["security"]["secret_key_file"].startswith("/etc/deepxpalm/keys/")
    assert operator["link"]["security"]["server_public_key_file"].startswith("/etc/deepxpalm/keys/")
