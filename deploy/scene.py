"""Scenes: one TOML file says which devices run, what they show, and the network.

A scene has a ``[robot]`` and an ``[operator]`` table (each node's own
config) and a ``[network]`` table for the link simulator. Each node reads
only its own table, so the same file can configure both machines.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

from common.config.overrides import apply_overrides
from common.config.typed import from_dict, load_toml, param
from common.errors import ConfigError
from operator_side.node.config import OperatorConfig
from robot_side.node.config import RobotConfig


@dataclass
class NetworkConfig:
    enabled: bool = param(True, "run the link simulator between the nodes")
    scenario: str = param("lan", "a named scenario (see `deepxpalm netsim --help`) or a TOML path")
    seed: int = param(0, "seeds every impairment: the same seed gives the same link")
    mode: str = param(
        "",
        "stream (TCP byte relay, CURVE passes) or message (per-message faults incl. "
        "corruption, plain only); empty = the scenario's (stream for every built-in one)",
    )


@dataclass
class SceneInfo:
    name: str = param("unnamed", "shown in logs and the live view")
    description: str = param("", "what this scene is for")


@dataclass
class Scene:
    scene: SceneInfo = param(SceneInfo(), "about this scene")
    robot: RobotConfig = param(RobotConfig(), "the robot node")
    operator: OperatorConfig = param(OperatorConfig(), "the operator node")
    network: NetworkConfig = param(NetworkConfig(), "the link between them")


SCENES_DIR = "deploy.scenes"


def scene_path(name_or_path: str) -> Path:
    """A shipped scene by name (``demo``) or any TOML file by path."""
    path = Path(name_or_path)
    if path.suffix == ".toml" or path.exists():
        if not path.exists():
            raise ConfigError(f"scene file {path} does not exist")
        return path
    shipped = resources.files(SCENES_DIR) / f"{name_or_path}.toml"
    if not shipped.is_file():
        names = sorted(
            p.name[:-5] for p in resources.files(SCENES_DIR).iterdir() if p.name.endswith(".toml")
        )
        raise ConfigError(f"no scene named {name_or_path!r}; shipped scenes: {names}")
    return Path(str(shipped))


def load_scene_dict(name_or_path: str, overrides: list[str] | None = None) -> dict[str, Any]:
    return apply_overrides(load_toml(scene_path(name_or_path)), overrides or [])


def load_scene(name_or_path: str, overrides: list[str] | None = None) -> Scene:
    return from_dict(Scene, load_scene_dict(name_or_path, overrides), where="")
