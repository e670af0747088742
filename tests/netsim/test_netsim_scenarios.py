"""Scenario files: every built-in loads, says where its figures come from, and merges right."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import pytest

from common.errors import ConfigError
from common.netsim.scenario import builtin_scenarios, load_scenario

REQUIRED = [
    "lan",
    "campus",
    "metro",
    "intercontinental",
    "4g",
    "leo_satellite",
    "geo_satellite",
    "bad_day",
]


def test_all_required_scenarios_ship() -> None:
    assert set(REQUIRED) <= set(builtin_scenarios())


@pytest.mark.parametrize("name", REQUIRED)
def test_builtin_loads_and_cites_its_figures(name: str) -> None:
    scenario = load_scenario(name)
    assert scenario.name == name and scenario.description
    text = resources.files("common.netsim.scenarios").joinpath(f"{name}.toml").read_text()
    assert "Source figures" in text
    for d in (scenario.to_operator, scenario.to_robot):
        assert d.delivery == "stream"  # ZeroMQ runs over TCP between the nodes


def test_directions_override_both() -> None:
    s = load_scenario("intercontinental")
    # Same propagation floor both ways, more queueing towards the operator.
    floor = s.to_operator.delay_quantile_ms(0.0)
    assert floor == pytest.approx(s.to_robot.delay_quantile_ms(0.0)) == pytest.approx(36.5)
    assert s.to_operator.jitter_ms > s.to_robot.jitter_ms
    assert s.to_robot.loss_percent == 0.1  # from [both]


def test_bad_day_has_an_outage_and_bursts() -> None:
    s = load_scenario("bad_day")
    assert s.to_operator.outages == [(20.0, 22.0)]
    assert s.to_operator.loss_model == "gilbert_elliott"


def test_custom_file(tmp_path: Path) -> None:
    path = tmp_path / "mine.toml"
    path.write_text(
        'description = "test"\n[both]\ndelivery = "datagram"\ndelay_ms = 5\n'
        "[to_robot]\nloss_percent = 2.5\n"
    )
    s = load_scenario(path)
    assert s.name == "mine"
    assert s.to_robot.loss_percent == 2.5 and s.to_operator.loss_percent == 0
    assert s.to_robot.delay_ms == 5


@pytest.mark.parametrize(
    ("body", "match"),
    [
        ("[both]\nlatency_ms = 5\n", "latency_ms"),
        ("[both]\ndistribution = 'cauchy'\n", "distribution"),
        ("[both]\nduplicate_percent = 1\n", "stream"),
        ("[to_robot]\noutages = [[3.0, 1.0]]\n", "outages"),
        ("delay_ms = 5\n", "delay_ms"),
    ],
)
def test_bad_files_are_config_errors_naming_the_key(tmp_path: Path, body: str, match: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(body)
    with pytest.raises(ConfigError, match=match):
        load_scenario(path)


def test_missing_file_and_unknown_name() -> None:
    with pytest.raises(ConfigError, match="does not exist"):
        load_scenario("/nonexistent/x.toml")
    with pytest.raises(ConfigError, match="built-in"):
        load_scenario("dialup")
