"""``deepxpalm netsim --help`` shows every default; options override them."""

from __future__ import annotations

import argparse
import contextlib
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


def test_sigusr1_cuts_the_link_both_ways_for_cut_s_and_says_when(tmp_path) -> None:
    """``kill -USR1``: a real ``deepxpalm netsim`` in datagram mode loses what is sent inside
    the window it reports to its supervisor, and forwards again after it."""
    import signal
    import socket

    from deploy.units.service import Service

    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(0.05)
    argv = ["netsim", "--scenario", "none", "--mode", "datagram", "--set", "netsim.cut_s=0.5"]
    argv += ["--robot-telemetry", f"udp://127.0.0.1:{rx.getsockname()[1]}"]
    argv += ["--operator-telemetry", "udp://127.0.0.1:0"]
    service = Service("netsim", argv, tmp_path / "netsim.log")
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        service.start()
        ready = service.up(30.0)
        host, _, port = ready.endpoints["operator_telemetry"].removeprefix("udp://").rpartition(":")
        sent: list[tuple[int, int]] = []  # (seq, monotonic ns just before the send)

        def send_for(seconds: float) -> None:
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                sent.append((len(sent), time.monotonic_ns()))
                tx.sendto(b"s" + sent[-1][0].to_bytes(4, "big"), (host, int(port)))
                time.sleep(0.01)

        send_for(0.3)
        service.popen.send_signal(signal.SIGUSR1)
        said = service.notify.wait_field("cut_ns", None, 5.0)
        assert said is not None, f"netsim never said it cut the link{service.log_tail()}"
        t1, t2 = (int(t) for t in said.split(","))
        assert t2 - t1 == 500_000_000
        send_for(max(0.0, (t2 - time.monotonic_ns()) / 1e9) + 0.4)
        # until the last one sent is in (a starved netsim forwards late, not never)
        got, last, deadline = set(), sent[-1][0], time.monotonic() + 5.0
        rx.settimeout(0.5)
        with contextlib.suppress(TimeoutError):
            while last not in got and time.monotonic() < deadline:
                got.add(int.from_bytes(rx.recv(64)[1:5], "big"))
    finally:
        service.stop()
        service.close()
        tx.close()
        rx.close()
    # a datagram is judged when netsim takes it: sent after t1, taken after it; 200 ms for
    # netsim's lag in taking it on a busy machine
    inside = {seq for seq, t in sent if t1 <= t <= t2 - 200_000_000}
    outside = {seq for seq, t in sent if t < t1 - 200_000_000 or t >= t2}
    assert inside and not inside & got, "datagrams sent during the cut were forwarded"
    assert outside and outside <= got, f"lost outside the cut: {sorted(outside - got)}"
    assert "link cut both ways for 0.5 s" in (tmp_path / "netsim.log").read_text()
