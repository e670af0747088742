"""``deepxpalm netsim --help`` shows every default; options override them."""

from __future__ import annotations

import argparse
import json
import os
import time

import pytest

from common.errors import ConfigError
from common.netsim import cli
from deploy.units.readiness import NotifySocket


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="deepxpalm netsim")
    cli.add_arguments(p)
    return p


def test_help_prints_defaults(capsys) -> None:
    with pytest.raises(SystemExit):
        _parser().parse_args(["--help"])
    out = capsys.readouterr().out
    assert 'scenario = "lan"' in out
    assert 'robot_telemetry = "tcp://127.0.0.1:5555"' in out
    assert 'operator_commands = "tcp://127.0.0.1:5566"' in out
    assert "seed = 0" in out


def test_options_override_scenario_and_endpoints() -> None:
    args = _parser().parse_args(
        [
            "--scenario",
            "none",
            "--seed",
            "7",
            "--delay-ms",
            "12",
            "--delay-to-robot-ms",
            "3",
            "--operator-telemetry",
            "tcp://127.0.0.1:6000",
        ]
    )
    config = cli.config_from_args(args)
    assert config.seed == 7
    assert config.endpoints.operator_telemetry == "tcp://127.0.0.1:6000"
    assert config.endpoints.robot_telemetry == "tcp://127.0.0.1:5555"
    scenario = cli.scenario_from_args(config, args)
    assert scenario.to_operator.delay_ms == 12.0
    assert scenario.to_robot.delay_ms == 3.0


def test_unknown_scenario_is_a_config_error() -> None:
    args = _parser().parse_args(["--scenario", "dialup"])
    with pytest.raises(ConfigError, match="built-in scenarios"):
        cli.scenario_from_args(cli.config_from_args(args), args)


def test_run_for_a_short_duration_returns_zero(tmp_path, monkeypatch) -> None:
    args = _parser().parse_args(
        [
            "--scenario",
            "none",
            "--duration-s",
            "0.2",
            "--robot-telemetry",
            "tcp://127.0.0.1:1",
            "--robot-commands",
            "tcp://127.0.0.1:2",
            "--operator-telemetry",
            "tcp://127.0.0.1:*",
            "--operator-commands",
            "tcp://127.0.0.1:*",
        ]
    )
    args.stats_file = tmp_path / "netsim.json"
    notify = NotifySocket("netsim")  # as systemd, or the demo, gives it
    monkeypatch.setenv("NOTIFY_SOCKET", notify.address)
    notify.started(os.getpid())
    before = time.monotonic_ns()
    try:
        assert cli.run(args) == 0
        deadline = time.monotonic() + 5
        while notify.ready is None and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        notify.close()
    stats = json.loads(args.stats_file.read_text())
    assert stats["scenario"] == "none"
    assert stats["directions"]["to_operator"]["received"] == 0
    # what a supervisor reads to know it forwards, and when its scenario's clock started
    ready = notify.ready
    assert ready is not None and ready.status.startswith("none")
    assert before <= int(ready.field("schedule_start_ns")) <= time.monotonic_ns()
    assert ready.endpoints["operator_telemetry"].startswith("tcp://127.0.0.1:")


def test_config_file_then_set_then_options(tmp_path) -> None:
    path = tmp_path / "scene.toml"
    path.write_text(
        '[netsim]\nscenario = "metro"\nseed = 3\n[netsim.endpoints]\n'
        'robot_telemetry = "tcp://127.0.0.1:7000"\n'
    )
    args = _parser().parse_args(
        [
            "--config",
            str(path),
            "--set",
            "netsim.seed=9",
            "--robot-commands",
            "tcp://127.0.0.1:7001",
        ]
    )
    config = cli.config_from_args(args)
    assert (config.scenario, config.seed) == ("metro", 9)
    assert config.endpoints.robot_telemetry == "tcp://127.0.0.1:7000"
    assert config.endpoints.robot_commands == "tcp://127.0.0.1:7001"
    assert cli.scenario_from_args(config, args).name == "metro"


def test_scenarios_run_as_a_byte_stream_unless_the_message_mode_is_asked_for() -> None:
    from common.netsim.proxy import LinkSimulator
    from common.netsim.stream import StreamForwarder

    for argv, kind in (
        (["--scenario", "bad_day"], StreamForwarder),
        (["--scenario", "bad_day", "--mode", "message"], LinkSimulator),
    ):
        config = cli.config_from_args(_parser().parse_args(argv))
        sim = cli.build_simulator(
            config, cli.scenario_from_args(config, _parser().parse_args(argv))
        )
        assert isinstance(sim, kind)
    datagram = cli.scenario_from_args(
        cli.config_from_args(_parser().parse_args([])), _parser().parse_args([])
    )
    datagram.to_operator.delivery = "datagram"
    with pytest.raises(ConfigError, match="message"):
        cli.build_simulator(cli.NetsimConfig(), datagram)
