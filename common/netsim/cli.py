"""``deepxpalm netsim``: run the link simulator between the two nodes.

Start the robot, then this, then point the operator at the simulator's bound
endpoints (by default ports 5565/5566 instead of 5555/5556). The stream
mode forwards TCP bytes (CURVE passes), the message mode re-publishes ZeroMQ
messages; the scenario says which, ``--mode`` overrides. The datagram mode
forwards UDP (a QUIC connection to a fabric router: its best-effort
datagrams lost one by one, never retransmitted) from
``--operator-telemetry udp://HOST:PORT`` to ``--robot-telemetry udp://HOST:PORT``. Settings come
from the defaults, then ``--config FILE`` (keys at the top level or under
``[netsim]``), then ``--set netsim.key=value``, then the explicit options.
``kill -USR1`` pulls the cable: the link is cut both ways for ``cut_s``.
"""

from __future__ import annotations

import argparse
import logging
import signal
import time
from dataclasses import dataclass
from typing import Any

from common.config.typed import param
from common.devices.lifecycle import as_hardware
from common.errors import ConfigError
from common.netsim.impairments import DIRECTIONS, Scenario
from common.netsim.proxy import Endpoints, LinkSimulator
from common.netsim.scenario import builtin_scenarios, load_scenario
from common.netsim.stream import StreamForwarder
from common.process.command_line import (
    add_config_arguments,
    load_node_config,
    print_config,
    write_stats,
)
from common.process.sd_notify import FIELD_PREFIX, Notifier
from common.process.signals import on_signal, stop_on_signals

log = logging.getLogger(__name__)


@dataclass
class NetsimConfig:
    """Everything ``deepxpalm netsim`` needs."""

    scenario: str = param("lan", "built-in scenario name, or a path to a scenario .toml")
    mode: str = param(
        "",
        "stream (TCP byte forwarder, CURVE passes), message (ZeroMQ) or datagram (UDP: a "
        "fabric router's QUIC; udp:// endpoints); empty = the scenario's",
    )
    seed: int = param(0, "same seed and scenario give the same impairment sequence")
    hwm: int = param(1000, "message mode: ZeroMQ high-water mark of each socket, in messages")
    spin_us: float = param(
        300.0, "busy-wait this long before each due time; sleeping wakes too late on a VM"
    )
    report_interval_s: float = param(5.0, "how often counters are logged; 0 = never")
    duration_s: float = param(0.0, "stop after this long; 0 = run until Ctrl-C")
    cut_s: float = param(
        5.0, "SIGUSR1 cuts the link both ways for this long from its arrival (a pulled cable)"
    )
    endpoints: Endpoints = param(Endpoints(), "")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_config_arguments(parser, NetsimConfig, "netsim", example="scenario=intercontinental")
    parser.epilog = f"Built-in scenarios: {', '.join(builtin_scenarios())}\n\n" + (
        parser.epilog or ""
    )
    parser.add_argument("--scenario", help="built-in scenario name or path to a .toml file")
    parser.add_argument("--seed", type=int, help="random seed of the impairments")
    parser.add_argument("--mode", choices=MODES, help="override the scenario's mode")
    parser.add_argument(
        "--delay-ms", type=float, help="base one-way delay in both directions (overrides scenario)"
    )
    for name in DIRECTIONS:
        parser.add_argument(
            f"--delay-{name.replace('_', '-')}-ms",
            dest=f"delay_{name}_ms",
            type=float,
            help=f"base one-way delay {name.replace('_', ' ')} (overrides --delay-ms)",
        )
    for key in _ENDPOINT_KEYS:
        parser.add_argument(f"--{key.replace('_', '-')}", dest=key, metavar="ENDPOINT")
    # the older spelling of --duration (add_config_arguments'), kept working and not shown
    parser.add_argument("--duration-s", dest="duration", type=float, help=argparse.SUPPRESS)


MODES = ("stream", "message", "datagram")
_ENDPOINT_KEYS = ("robot_telemetry", "robot_commands", "operator_telemetry", "operator_commands")


def config_from_args(args: argparse.Namespace) -> NetsimConfig:
    """Defaults, then ``--config``, then ``--set``, then the explicit options."""
    config = load_node_config(args, NetsimConfig, "netsim")
    for key in _ENDPOINT_KEYS:
        value = getattr(args, key, None)
        if value is not None:
            setattr(config.endpoints, key, value)
    if getattr(args, "duration", None) is not None:  # --duration, as every command takes it
        config.duration_s = args.duration
    for key in ("scenario", "seed", "duration_s", "mode"):
        value = getattr(args, key, None)
        if value is not None:
            setattr(config, key, value)
    if not config.cut_s > 0:
        raise ConfigError(f"netsim.cut_s must be > 0 s (a cut's length), not {config.cut_s}")
    return config


def scenario_from_args(config: NetsimConfig, args: argparse.Namespace) -> Scenario:
    """The configured scenario with any ``--delay*`` overrides applied."""
    scenario = load_scenario(config.scenario)
    for name in DIRECTIONS:
        delay = getattr(args, f"delay_{name}_ms", None)
        if delay is None:
            delay = getattr(args, "delay_ms", None)
        if delay is not None:
            if delay < 0:
                raise ConfigError(f"delay must be >= 0 ms, not {delay}")
            scenario = scenario.with_delay(name, delay)
    return scenario


def run(args: argparse.Namespace) -> int:
    """The link simulator, at the simulated hardware's priority where it may (``as_hardware``):
    a network path does not wait for the PC's CPU, and a simulator starved by the nodes it
    links delays what it forwards, turning a LAN scenario into a congested one that nothing
    configured. Its forwarding threads start at this thread's niceness."""
    return as_hardware(_run)(args)


def _run(args: argparse.Namespace) -> int:
    config = config_from_args(args)
    if getattr(args, "print_config", False):
        print_config(config, "netsim")
        return 0
    scenario = scenario_from_args(config, args)
    old = signal.getsignal(signal.SIGTERM)
    done = stop_on_signals((signal.SIGTERM,))  # Ctrl-C stays a KeyboardInterrupt
    sim = build_simulator(config, scenario)
    notifier = Notifier()
    on_signal(signal.SIGUSR1, lambda: _cut(sim, config.cut_s, notifier))
    try:
        sim.start()
        log.warning(
            "netsim running scenario %r (%s mode, seed %d): operator connects to %s "
            "(telemetry) and %s (commands); schedule_start_ns=%d (monotonic: outages count "
            "from it)",  # datagram mode: both are its one UDP address
            scenario.name,
            mode_of(config, scenario),
            config.seed,
            sim.operator_telemetry_endpoint,
            sim.operator_commands_endpoint,
            sim.start_ns,
        )
        # READY=1 once forwarding (systemd, or whoever started it): where the operator
        # connects (a port-0 config's ports too) and when the scenario's clock started
        notifier.ready(
            f"{scenario.name} ({mode_of(config, scenario)} mode)",
            {
                "operator_telemetry": sim.operator_telemetry_endpoint,
                "operator_commands": sim.operator_commands_endpoint,
            },
            schedule_start_ns=sim.start_ns,
        )
        t_end = time.monotonic() + config.duration_s if config.duration_s > 0 else None
        t_report = time.monotonic()
        while not done.is_set():
            now = time.monotonic()
            if t_end is not None and now >= t_end:
                break
            if sim.error is not None:
                log.error("netsim stopped: %r", sim.error)
                return 1
            if config.report_interval_s > 0 and now - t_report >= config.report_interval_s:
                t_report = now
                for name, c in sim.counters().items():
                    log.info("%s: %s", name, c)
            done.wait(0.1)
    except KeyboardInterrupt:
        pass
    finally:
        sim.stop()
        signal.signal(signal.SIGTERM, old)
    summary = final_stats(sim)
    for name, c in summary["directions"].items():
        log.info("final %s: %s", name, c)
    write_stats(getattr(args, "stats_file", None), summary)
    return 0


def mode_of(config: NetsimConfig, scenario: Scenario) -> str:
    """The configured mode, or the scenario's when none is configured."""
    mode = config.mode or scenario.mode
    if mode not in MODES:
        raise ConfigError(f"netsim mode must be one of {', '.join(MODES)}, not {mode!r}")
    return mode


def udp_address(endpoint: str, what: str) -> tuple[str, int]:
    """(host, port) of ``udp://HOST:PORT``; ConfigError naming the setting otherwise."""
    host, sep, port = endpoint.removeprefix("udp://").rpartition(":")
    if not endpoint.startswith("udp://") or not sep or not port.isdigit():
        raise ConfigError(f"netsim {what} must be udp://HOST:PORT in datagram mode: {endpoint!r}")
    return host.strip("[]"), int(port)


class DatagramLink:
    """The datagram forwarder with the face ``run`` expects of a simulator."""

    def __init__(self, config: NetsimConfig, scenario: Scenario) -> None:
        from common.netsim.datagram import DatagramForwarder

        self.scenario = scenario
        self.seed = config.seed
        self.forwarder = DatagramForwarder(
            scenario,
            target=udp_address(config.endpoints.robot_telemetry, "robot_telemetry"),
            listen=udp_address(config.endpoints.operator_telemetry, "operator_telemetry"),
            seed=config.seed,
            spin_us=config.spin_us,
        )
        self.operator_telemetry_endpoint = self.operator_commands_endpoint = ""

    def start(self) -> None:
        self.forwarder.start()
        host, port = self.forwarder.address
        self.operator_telemetry_endpoint = self.operator_commands_endpoint = f"udp://{host}:{port}"

    @property
    def start_ns(self) -> int | None:
        return self.forwarder.start_ns

    @property
    def error(self) -> BaseException | None:
        return self.forwarder.error

    def counters(self) -> dict[str, dict[str, Any]]:
        return self.forwarder.counters()

    def own_latency_ns(self) -> list[int]:
        return self.forwarder.own_latency_ns()

    def cut(self, seconds: float) -> tuple[int, int]:
        return self.forwarder.cut(seconds)

    def stop(self) -> None:
        self.forwarder.stop()


def _cut(sim: LinkSimulator | StreamForwarder | DatagramLink, seconds: float, notifier: Notifier):
    """SIGUSR1: the link cut both ways from now, said to the log and to whoever supervises
    (``X_DEEPXPALM_CUT_NS=t1,t2``, monotonic ns: a test judges the fault from its real start)."""
    t1, t2 = sim.cut(seconds)
    log.warning("netsim: link cut both ways for %.1f s (SIGUSR1)", seconds)
    notifier.send(f"{FIELD_PREFIX}CUT_NS={t1},{t2}")


def build_simulator(
    config: NetsimConfig, scenario: Scenario
) -> LinkSimulator | StreamForwarder | DatagramLink:
    """The byte-stream forwarder, the message-level simulator or the datagram forwarder."""
    mode = mode_of(config, scenario)
    if mode == "datagram":
        return DatagramLink(config, scenario)
    if mode == "stream":
        return StreamForwarder(
            scenario,
            endpoints=config.endpoints,
            seed=config.seed,
            spin_us=config.spin_us,
        )
    return LinkSimulator(
        scenario,
        endpoints=config.endpoints,
        seed=config.seed,
        hwm=config.hwm,
        spin_us=config.spin_us,
    )


def final_stats(sim: LinkSimulator | StreamForwarder | DatagramLink) -> dict[str, Any]:
    """Counters per direction and the simulator's own per-send cost, JSON-able."""
    own = sorted(sim.own_latency_ns())
    mode = {StreamForwarder: "stream", DatagramLink: "datagram"}.get(type(sim), "message")
    out: dict[str, Any] = {
        "scenario": sim.scenario.name,
        "mode": mode,
        "seed": sim.seed,
        "directions": sim.counters(),
    }
    if isinstance(sim, StreamForwarder):
        out["connections"] = sim.connection_counts()
    if own:
        out["own_latency_us"] = {
            "p50": own[len(own) // 2] / 1e3,
            "p99": own[min(len(own) - 1, int(0.99 * len(own)))] / 1e3,
            "n": len(own),
        }
    return out
