"""Scenarios: named link presets as TOML files, or a custom file by path.

A file has ``name`` and ``description``, then impairment keys in
``[both]`` (applied to both directions) and ``[to_operator]`` /
``[to_robot]`` tables that override them per direction. Real paths are
asymmetric (uplink and downlink differ on 4G and satellite), which is why
the directions are separate, and mostly symmetric, which is why ``[both]``
exists.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Any

from common.config.typed import from_dict, load_toml
from common.errors import ConfigError
from common.netsim.impairments import DIRECTIONS, Scenario

_PACKAGE = "common.netsim.scenarios"


def builtin_scenarios() -> list[str]:
    """Names of the scenarios shipped with the package."""
    files = resources.files(_PACKAGE).iterdir()
    return sorted(f.name[: -len(".toml")] for f in files if f.name.endswith(".toml"))


def scenario_from_dict(
    data: dict[str, Any], *, where: str = "scenario", base_dir: Path | None = None
) -> Scenario:
    """Build a ``Scenario``, merging ``[both]`` under each direction's own table.

    A relative ``trace_file`` is taken relative to ``base_dir`` (the
    scenario file's folder), so a scenario and its trace travel together.
    """
    data = dict(data)
    both = data.pop("both", {}) or {}
    if not isinstance(both, dict):
        raise ConfigError(f"[{where}.both] must be a table")
    for name in DIRECTIONS:
        own = data.get(name, {}) or {}
        if not isinstance(own, dict):
            raise ConfigError(f"[{where}.{name}] must be a table")
        merged = {**both, **own}
        trace = merged.get("trace_file")
        if isinstance(trace, str) and trace and base_dir is not None:
            merged["trace_file"] = str((base_dir / trace).resolve())
        data[name] = merged
    return from_dict(Scenario, data, where=where)


def load_scenario(name_or_path: str | Path) -> Scenario:
    """A built-in scenario by name, or a TOML file by path (anything with / or .toml)."""
    text = str(name_or_path)
    if isinstance(name_or_path, Path) or "/" in text or text.endswith(".toml"):
        path = Path(text)
        data = load_toml(path)
        data.setdefault("name", path.stem)
        return scenario_from_dict(data, where=path.name, base_dir=path.parent)
    known = builtin_scenarios()
    if text not in known:
        raise ConfigError(
            f"unknown scenario {text!r}; built-in scenarios are {known}, "
            "or give a path to a .toml file"
        )
    ref = resources.files(_PACKAGE).joinpath(f"{text}.toml")
    with resources.as_file(ref) as path:
        data = load_toml(path)
        return scenario_from_dict(data, where=f"{text}.toml", base_dir=path.parent)
