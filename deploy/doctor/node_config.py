"""The node's own config: does it parse, and does the CNN it names load?"""

from __future__ import annotations

from typing import Any

from common.config.typed import from_dict
from common.devices.preflight import FAIL, PASS
from common.errors import ConfigError, DeepXPalmError
from deploy.doctor.report import ROLES, Report


def node_section(data: dict[str, Any], role: str) -> dict[str, Any]:
    """The node's own table, the way ``load_node_config`` picks it."""
    if isinstance(data.get(role), dict):
        return data[role]
    if any(k in data for k in ("robot", "operator", "network", "scene")):
        return {}
    return data


def infer_role(data: dict[str, Any]) -> str | None:
    """The node a file configures when it names only one."""
    present = [r for r in ROLES if isinstance(data.get(r), dict)]
    return present[0] if len(present) == 1 else None


def _config_class(role: str) -> type:
    if role == "robot":
        from robot_side.node.config import RobotConfig

        return RobotConfig
    from operator_side.node.config import OperatorConfig

    return OperatorConfig


def check_config(report: Report, role: str, data: dict[str, Any]) -> Any | None:
    """Parse the table as the node does; None when it would not start."""
    try:
        config = from_dict(_config_class(role), data, where=role)
    except ConfigError as e:
        report.add(
            "config",
            FAIL,
            str(e),
            f"correct that key; `deepxpalm {role} --help` lists every setting with its default",
        )
        return None
    report.add("config", PASS, f"{role} config valid ({report.source})")
    if role == "robot" and config.render.mode == "mask":
        try:
            from robot_side.perception import load_classifier

            clf = load_classifier(config.classifier.path, backend=config.classifier.backend)
            report.add("classifier", PASS, f"{clf.path.name} loads with backend {clf.backend}")
        except (DeepXPalmError, OSError, ValueError) as e:
            report.add(
                "classifier",
                FAIL,
                f"cannot load the CNN: {e}",
                "install the robot extra (pip install 'deepxpalm[robot]'), or fix "
                "robot.classifier.path / backend, or set robot.render.mode = 'direct'",
            )
    return config
