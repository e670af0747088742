"""``deepxpalm demo``: both nodes, simulated devices and the link simulator, one command.

Every node runs as a child process, as it would on its own machine: the
robot node, the link simulator, the operator node (``deepxpalm operator``,
which writes what it shows to a status file), and the simulated servo bus
(``deepxpalm sim servos``) on a pty whose path survives its restarts. The
demo draws the live view from the operator's status file (or prints one JSON
summary with ``--json``) and hands the keys to the operator over its stdin.
Latency comes from the messages' timestamps.

A child that dies while the demo runs is restarted as its systemd unit would
be (``deploy/supervisor.py``); the live view and the summary say so. The
operator runs under its unit's rules: its watchdog ends a frozen node, and
after any end of the node ``deepxpalm palm lift`` opens the servo bus and
lifts the linkages off the palm before the node is started again.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import json
import logging
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from common.cli_support import add_overrides_argument, stop_on_signals
from common.config import check_secret_file, config_toml, from_dict
from common.errors import ConfigError
from common.signing import write_secret_file
from common.transport import free_loopback_ports
from deploy import live_view
from deploy.scene import Scene, load_scene_dict, scene_path
from deploy.supervisor import (
    DEFAULT_RESTART_S,
    Child,
    StopPost,
    Supervisor,
    stop_post_args,
    terminate,
    unit_restart_s,
)
from deploy.unit_policy import policy, set_niceness, unit_nice
from deploy.watchdog import UnitWatchdog
from operator_side.dashboard.config import TOKEN_ENV, VIDEO_OVER_LINK

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--scene", default="demo", help="shipped scene name or TOML path (default: demo)"
    )
    parser.add_argument(
        "--duration", type=float, help="stop after this many seconds (default: Ctrl-C)"
    )
    parser.add_argument(
        "--json", action="store_true", help="no live view; print one JSON summary at the end"
    )
    parser.add_argument("--scenario", help="network scenario, overriding the scene's")
    parser.add_argument("--no-netsim", action="store_true", help="connect the nodes directly")
    link = parser.add_mutually_exclusive_group()
    link.add_argument(
        "--curve",
        action="store_true",
        help="encrypt and authenticate the link with CURVE keys made for this run (the "
        "default; the simulator relays the encrypted bytes)",
    )
    link.add_argument(
        "--plain",
        action="store_true",
        help="plain TCP between the nodes: ANY process on this machine can then steer the "
        "arm, open the gripper and watch the camera through the robot's command port "
        "(needed only for the simulator's message mode, which re-publishes messages)",
    )
    link.add_argument(
        "--fabric",
        action="store_true",
        help="across sites: the nodes meet through a Zenoh router made for the run (a roster, "
        "its certificates, signed commands); the link simulator carries the operator's QUIC "
        "connection to it, datagram by datagram",
    )
    parser.add_argument(
        "--record", type=Path, metavar="DIR", help="record robot.mcap and operator.mcap here"
    )
    parser.add_argument(
        "--dashboard", action="store_true", help="serve the live web dashboard (URL shown)"
    )
    parser.add_argument(
        "--no-video",
        action="store_true",
        help="no camera in the dashboard or the recording (default: the lab's camera, or the "
        "test pattern, when the video extra is installed)",
    )
    add_overrides_argument(parser, "robot.render.mode=direct")


def die_with_parent() -> None:
    """In the child: SIGTERM when the demo dies, even by SIGKILL (Linux), so nothing lingers."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def spawn_cli(
    args: list[str],
    log_path: Path,
    unit: str | None = None,
    *,
    stdin: int | None = None,
    env: dict[str, str] | None = None,
) -> subprocess.Popen:
    """``deepxpalm ARGS`` as a child of the demo; at the priority of its systemd ``unit``,
    with ``env`` added to ours (a notify socket) and ``stdin`` (a pipe for commands)."""
    out = log_path.open("ab")  # a restarted child's log follows its crash
    nice = unit_nice(unit)

    def in_child() -> None:
        die_with_parent()
        set_niceness(nice)

    return subprocess.Popen(
        [sys.executable, "-m", "deploy.cli", *args],
        stdin=stdin,
        stdout=out,
        stderr=subprocess.STDOUT,
        env=None if env is None else {**os.environ, **env},
        start_new_session=True,  # Ctrl-C reaches the demo only; it stops the children in order
        preexec_fn=in_child,
    )


def wait_for_robot(node: Any, procs: list, stop: threading.Event, errors: list[str]) -> None:
    """Until an operator node of this process hears the robot, at most 60 s."""
    wait_until_heard(lambda: node.counters["heartbeats_received"] > 0, procs, stop, errors)


def wait_until_heard(
    heard: Callable[[], bool], procs: list, stop: threading.Event, errors: list[str]
) -> None:
    """Until the operator hears the robot (devices connected, simulators up), at most 60 s."""
    deadline = time.monotonic() + 60
    while not stop.is_set() and time.monotonic() < deadline:
        if heard():
            return
        if any(proc.poll() is not None for _, proc, _ in procs):
            return  # reported by the main loop
        stop.wait(0.05)
    if not stop.is_set():
        errors.append("the robot node did not start within 60 s")


def stop_child(proc: subprocess.Popen, name: str, errors: list[str], log_path: Path) -> None:
    """SIGTERM, as systemd stops a unit, then SIGKILL after 10 s (reported as an error).

    Not SIGINT: a shell without job control starts background commands with
    SIGINT ignored, and its children inherit that (Python then installs no
    KeyboardInterrupt handler); a demo or test run launched that way left
    every child deaf to Ctrl-C and killed after 10 s. No shell ignores SIGTERM.
    """
    if proc.poll() is None:
        terminate(proc)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            errors.append(f"{name} did not stop within 10 s and was killed")
    if proc.returncode not in (0, -signal.SIGINT, 130, -signal.SIGTERM, 143):
        tail = log_path.read_text(errors="replace").strip().splitlines()[-5:]
        errors.append(f"{name} exited with {proc.returncode}: " + " | ".join(tail))


def netsim_args(scene: Scene, endpoints: tuple[str, str, str, str]) -> list[str]:
    """``deepxpalm netsim`` between the robot's (telemetry, commands) and the operator's."""
    robot_tel, robot_cmd, op_tel, op_cmd = endpoints
    net = scene.network
    return [
        "netsim",
        *("--scenario", net.scenario, "--seed", str(net.seed)),
        *(["--mode", net.mode] if net.mode else []),
        *("--robot-telemetry", robot_tel, "--robot-commands", robot_cmd),
        *("--operator-telemetry", op_tel, "--operator-commands", op_cmd),
    ]


def fit_command_timing(scene: Scene) -> None:
    """Widen the robot's command age, deadman and jog time to the scenario's command delay,
    and the operator's blind-jog and signed-telemetry age limits to its telemetry delay.

    The robot judges commands by the operator's send time, so on a link slower
    than ``max_command_age_ms`` (a GEO satellite) nothing would ever be fresh
    and the arm would never move. A real deployment sets these by hand
    (docs/protocol.md); the demo sets them from the scenario it simulates.
    """
    from common.netsim.scenario import load_scenario

    scenario = load_scenario(scene.network.scenario)
    to_operator = scenario.direction("to_operator")
    # the operator holds its jogs when the robot's telemetry is older than this (by send time)
    seen_ms = to_operator.delay_ms + 4 * to_operator.jitter_ms + 100.0
    op_link = scene.operator.link
    op_link.jog_blind_after_ms = max(op_link.jog_blind_after_ms, seen_ms)
    to_robot = scenario.direction("to_robot")
    # signed telemetry: a restarted robot is believed by a heartbeat answering ours (a round trip)
    round_trip_ms = (
        to_operator.delay_ms + to_robot.delay_ms + 4 * (to_operator.jitter_ms + to_robot.jitter_ms)
    )
    op_link.max_telemetry_age_ms = max(op_link.max_telemetry_age_ms, round_trip_ms + 100.0)
    needed_ms = to_robot.delay_ms + 4 * to_robot.jitter_ms + 100.0  # + heartbeat period, slack
    link = scene.robot.link
    if needed_ms <= link.max_command_age_ms:
        return
    link.max_command_age_ms = needed_ms
    link.deadman_ms = max(link.deadman_ms, needed_ms)
    if scene.robot.arm.get("kind", "none") != "none":
        limits = scene.robot.arm.setdefault("limits", {})
        limits["jog_timeout_s"] = max(limits.get("jog_timeout_s", 0.25), needed_ms / 1e3)
    log.warning(
        "scenario %s: commands take %.0f ms to reach the robot; command age, deadman and jog "
        "time raised to %.0f ms",
        scene.network.scenario,
        to_robot.delay_ms,
        needed_ms,
    )


LAB_DEVICES = ("tactile", "gripper", "arm")
WORLD_START_S = 60.0


def start_lab_world(
    scene: Scene, workdir: Path
) -> tuple[subprocess.Popen, Path, str | None] | None:
    """The simulated lab as its own process, when the scene's devices live in one.

    Its addresses file then points the robot's lab devices (``running_world``)
    and the video server's lab camera at it: (process, addresses, world
    config). None when no device is a lab kind, or one already names a
    running world.
    """
    sections = [getattr(scene.robot, d) for d in LAB_DEVICES]
    lab = [s for s in sections if s.get("kind") == "lab"]
    if not lab or any(s.get("running_world") for s in lab):
        return None
    configs = {str(s["world_config"]) for s in lab if s.get("world_config")}
    if len(configs) > 1:
        raise ConfigError(f"the scene's lab devices name different worlds: {sorted(configs)}")
    addresses = workdir / "world.json"
    config = configs.pop() if configs else None
    proc = spawn_lab_world(addresses, config, workdir / "world.log")
    for section in lab:
        section["running_world"] = str(addresses)
    return proc, addresses, config


def spawn_lab_world(addresses: Path, config: str | None, log_path: Path) -> subprocess.Popen:
    """``python -m robot_side.lab``, once it has written ``addresses`` (a stale one removed)."""
    addresses.unlink(missing_ok=True)
    args = [sys.executable, "-m", "robot_side.lab", "--addresses-file", str(addresses)]
    if config is not None:
        args += ["--config", config]
    from common.devices import SIMULATED_HARDWARE_NICE  # the world is the lab's hardware

    def in_child() -> None:
        die_with_parent()
        set_niceness(SIMULATED_HARDWARE_NICE)

    proc = subprocess.Popen(
        args,
        stdout=subprocess.DEVNULL,
        stderr=log_path.open("ab"),
        start_new_session=True,
        preexec_fn=in_child,
    )
    deadline = time.monotonic() + WORLD_START_S
    while not addresses.exists():
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            tail = log_path.read_text(errors="replace").strip().splitlines()[-5:]
            raise ConfigError(f"the lab world did not start: {' | '.join(tail)}")
        time.sleep(0.1)
    return proc


def video_wanted(args: argparse.Namespace, scene: Scene) -> bool:
    """A camera for the dashboard or the recording, when the video extra is here."""
    if args.no_video or not (args.dashboard or scene.operator.dashboard.enabled or args.record):
        return False
    if importlib.util.find_spec("aiortc") is None:
        log.info("no camera: the video extra (aiortc) is not installed")
        return False
    return True


def video_args(
    world_addresses: Path | None, token_file: Path, scenario: str = "", seed: int = 0
) -> tuple[list[str], str]:
    """``deepxpalm video`` on a free loopback port: the lab's camera, or the test pattern.

    Its signalling secret is in ``token_file`` (the robot node reads it there, so the
    secret never appears on a command line); its media stays on loopback, and crosses
    the link simulator's datagram mode under ``scenario`` when there is one.
    """
    port = free_loopback_ports(1)[0]
    settings = [f"port={port}", f'token_file="{token_file}"', 'media_interfaces=["lo"]']
    if scenario:
        settings += [f'link_scenario="{scenario}"', f"link_seed={seed}"]
    if world_addresses is not None:
        settings += ['source="lab"', f'lab.addresses_file="{world_addresses}"']
    else:
        settings += ["test_pattern.width=320", "test_pattern.height=240", "test_pattern.fps=15"]
    return ["video", *(a for s in settings for a in ("--set", s))], f"ws://127.0.0.1:{port}/"


def run(args: argparse.Namespace) -> int:
    data = load_scene_dict(args.scene, args.overrides)
    scene: Scene = from_dict(Scene, data, where="")
    check_secret_file(scene_path(args.scene), scene)
    if args.scenario:
        scene.network.scenario = args.scenario
    use_netsim = scene.network.enabled and not args.no_netsim
    workdir = Path(tempfile.mkdtemp(prefix="deepxpalm-demo-"))
    robot_tel, robot_cmd, op_tel, op_cmd = (f"tcp://127.0.0.1:{p}" for p in free_loopback_ports(4))
    scene.robot.link.telemetry_endpoint = robot_tel
    scene.robot.link.command_endpoint = robot_cmd
    scene.operator.link.telemetry_endpoint = op_tel if use_netsim else robot_tel
    scene.operator.link.command_endpoint = op_cmd if use_netsim else robot_cmd
    if use_netsim:
        fit_command_timing(scene)
    fabric = None
    if args.fabric:
        from deploy.demo_fabric import use_fresh_fabric

        fabric = use_fresh_fabric(scene, workdir / "fabric", use_netsim)
    elif demo_link_is_plain(args, scene, use_netsim):
        scene.robot.link.allow_plain_commands = True
        log.warning(
            "--plain: the robot's command port %s%s takes commands from any process on this "
            "machine",
            robot_cmd,
            f" and the link simulator's {op_cmd}" if use_netsim else "",
        )
    else:
        _use_fresh_curve_keys(scene, workdir / "keys")
    children = Supervisor()
    world = start_lab_world(scene, workdir)
    video = None
    if video_wanted(args, scene):
        token_file = workdir / "video.token"
        video, video_url = video_args(
            world[1] if world is not None else None,
            token_file,
            scene.network.scenario if use_netsim else "",
            scene.network.seed,
        )
        scene.robot.link.video_url = video_url  # offers reach it through the robot's link
        scene.robot.link.video_token_file = token_file
        scene.operator.dashboard.video_url = VIDEO_OVER_LINK
    if world is not None:
        world_proc, addresses, world_config = world
        world_log = workdir / "world.log"
        children.add(
            Child(
                "world",
                lambda n: (
                    world_proc if n == 0 else spawn_lab_world(addresses, world_config, world_log)
                ),
                world_log,
                DEFAULT_RESTART_S,
                restarts_too=("robot", "video"),  # they found it by its addresses
            )
        )
    robot_cfg = workdir / "robot.toml"
    robot_cfg.write_text(config_toml(scene.robot, "robot", redact=False))  # in our 0700 dir
    errors: list[str] = []
    stop = stop_on_signals()
    robot_stats_path = workdir / "robot-stats.json"
    netsim_stats_path = workdir / "netsim-stats.json"
    verbosity = ["-v"] if logging.getLogger().level <= logging.INFO else []

    def robot_args(n: int) -> list[str]:
        args_ = [*verbosity, "robot", "--config", str(robot_cfg)]
        args_ += ["--stats-file", str(robot_stats_path)]
        if args.record:  # a restarted node records beside the crashed one's file, not over it
            name = "robot.mcap" if n == 0 else f"robot.restart{n}.mcap"
            args_ += ["--record", str(args.record / name)]
        return args_

    def cli_child(name: str, argv: Callable[[int], list[str]], **kw: Any) -> None:
        log_path = workdir / f"{name}.log"
        children.add(Child(name, lambda n: spawn_cli(argv(n), log_path, name), log_path, **kw))

    cli_child("robot", robot_args, restart_delay_s=unit_restart_s("robot"))
    if fabric is not None:
        router = [*verbosity, "router", "--config", str(fabric.router_config)]
        cli_child("router", lambda n: router, restart_delay_s=unit_restart_s("router"))
    if use_netsim and fabric is not None:
        netsim = [
            *verbosity,
            "netsim",
            *("--scenario", scene.network.scenario, "--seed", str(scene.network.seed)),
            *("--mode", "datagram", "--robot-telemetry", fabric.router_udp),
            *("--operator-telemetry", fabric.netsim_udp),
            *("--stats-file", str(netsim_stats_path)),
        ]
        cli_child("netsim", lambda n: netsim, restart_delay_s=DEFAULT_RESTART_S)
    elif use_netsim:
        netsim = [
            *verbosity,
            *netsim_args(scene, (robot_tel, robot_cmd, op_tel, op_cmd)),
            *("--stats-file", str(netsim_stats_path)),
        ]
        cli_child("netsim", lambda n: netsim, restart_delay_s=DEFAULT_RESTART_S)
    if video is not None:  # -v: it says when the camera opens and closes

        def video_args_(n: int) -> list[str]:
            if not args.record:
                return ["-v", *video]
            # the camera beside the robot's recording; a restarted server's file beside it
            name = "camera.mcap" if n == 0 else f"camera.restart{n}.mcap"
            return ["-v", *video, "--set", f'record="{args.record / name}"']

        cli_child(
            "video",
            video_args_,
            restart_delay_s=unit_restart_s("video"),
            essential=False,  # the demo runs on without a camera
        )
    servos = servo_simulator(scene, workdir)
    if servos is not None:
        servo_args, servo_log = servos
        children.add(
            Child(
                "servos",
                lambda n: spawn_servo_simulator(servo_args, servo_log, first=n == 0),
                servo_log,
                DEFAULT_RESTART_S,
                # a bus that came back is opened again by a new node (its pty is a new one)
                restarts_too=("operator",),
            )
        )
    operator = OperatorChild(args, scene, workdir, verbosity, keyboard=not args.json)
    children.add(operator.child())
    status = live_view.OperatorStatus(operator.status_path)
    wait_until_heard(status.heard_robot, children.procs(), stop, errors)
    children.armed = status.heard_robot()  # up: from now on, restart
    deadline = time.monotonic() + 10
    while not children.armed and not stop.is_set() and time.monotonic() < deadline:
        if not children.poll(errors):  # a child that ended while starting: its log's tail
            break
        stop.wait(SUPERVISE_PERIOD_S)
    t0 = time.monotonic()  # --duration counts from the first word of the robot
    keyboard = live_view.Keyboard() if not args.json else contextlib.nullcontext()
    dashboard_line = ""
    try:
        if scene.operator.dashboard.enabled and children.armed:
            url = status.dashboard_url()
            if url is None:
                errors.append(f"the operator node named no dashboard; see {operator.log_path}")
            else:
                url_file = workdir / "dashboard.url"  # with its token, 0600 in a 0700 dir
                write_secret_file(url_file, url + "\n")
                # the token once, at start (scripts read this line); never again after it
                print(f"dashboard {url}", file=sys.stderr, flush=True)
                dashboard_line = live_view.dashboard_line(url, url_file)
        next_view = 0.0
        with keyboard:
            while not stop.is_set() and children.armed:
                now = time.monotonic()
                elapsed = now - t0
                if args.duration is not None and elapsed >= args.duration:
                    break
                if not children.poll(errors):  # every tick: the watchdog, a dead child
                    stop.set()
                if not args.json and now >= next_view:
                    next_view = now + VIEW_PERIOD_S
                    for action, kwargs in keyboard.commands():
                        operator.send(children.children["operator"], action, kwargs)
                    snap = status.snapshot()
                    view = (
                        live_view.render(snap, scene.scene.name, elapsed)
                        if snap is not None
                        else "\x1b[H\x1b[2Jthe operator node is starting\n"
                    )
                    sys.stdout.write(view + children.status_line() + "\n" + dashboard_line)
                    sys.stdout.flush()
                stop.wait(SUPERVISE_PERIOD_S)
    finally:
        ran_s = time.monotonic() - t0
        stop.set()
        children.stop_all(stop_child, errors)
    summary = _summary(scene, status, ran_s, robot_stats_path, netsim_stats_path, errors)
    summary["processes"] = children.summary()
    summary["logs"] = str(workdir)
    print(json.dumps(summary, indent=2))
    return 1 if errors else 0


#: how often the demo's supervisor looks at its children: a dead operator's palm lift starts
#: within this, and a frozen one's watchdog is checked as often
SUPERVISE_PERIOD_S = 0.02
#: how often the live view is drawn (and the keys read)
VIEW_PERIOD_S = 0.05


def servo_simulator(scene: Scene, workdir: Path) -> tuple[list[str], Path] | None:
    """``deepxpalm sim servos`` for a scene whose palm is simulated, its pty at a fixed path.

    The operator node then drives it as a real bus (``kind = "feetech"``, the
    scene's driver settings, the pty's path for the port), so the bus outlives
    the node and a ``deepxpalm palm lift`` can open it once the node is gone.
    The bus's front panel (its goals, every goal write and torque off) is
    ``servos-status.json`` in the demo's directory. None: the scene's servos
    are not simulated.
    """
    servos = scene.operator.servos
    if servos.get("kind") != "simulated_feetech":
        return None
    from operator_side.servos.sts_sim import SimulatedFeetechConfig, simulated_driver_settings

    settings = {k: v for k, v in servos.items() if k != "kind"}
    sim = from_dict(SimulatedFeetechConfig, settings, where="operator.servos")
    link_dir = workdir / "servo-link"
    sim.bus.link_dir = link_dir
    config = workdir / "sim-servos.toml"
    config.write_text(config_toml(sim.bus))
    driver = simulated_driver_settings(sim)
    driver.update(settings.get("driver", {}))  # what the scene set for the driver
    scene.operator.servos = {**driver, "kind": "feetech", "port": str(link_dir / "sts-bus")}
    status = workdir / "servos-status.json"
    args = ["sim", "servos", "--config", str(config), "--status-file", str(status)]
    return args, workdir / "servos.log"


SERVOS_START_S = 60.0


def spawn_servo_simulator(args: list[str], log_path: Path, first: bool) -> subprocess.Popen:
    """The bus simulator; the first one waited for until it serves its pty (the node opens
    it at start). A restarted one serves the same path."""
    start = log_path.stat().st_size if log_path.exists() else 0
    proc = spawn_cli(args, log_path)
    deadline = time.monotonic() + SERVOS_START_S
    while first:
        text = log_path.read_bytes()[start:].decode(errors="replace")
        if '{"simulator"' in text:
            break
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            raise ConfigError(f"the servo bus simulator did not start: {text[-1000:]}")
        time.sleep(0.05)
    return proc


class OperatorChild:
    """``deepxpalm operator`` as the demo's child, under its unit's rules.

    Its config (the scene's operator with the run's keys and ports) is a 0600
    file in the demo's directory; it writes its live view, counters and
    dashboard address to ``operator-status.json``; the keys reach it as JSON
    lines on its stdin. It runs with its unit's watchdog (a notify socket in
    the demo's directory) and, when its servos are a bus of their own, its
    unit's ``ExecStopPost=`` (``deepxpalm palm lift``) after every end.
    """

    def __init__(
        self,
        args: argparse.Namespace,
        scene: Scene,
        workdir: Path,
        verbosity: list[str],
        keyboard: bool,
    ) -> None:
        self.args, self.scene, self.verbosity, self.keyboard = args, scene, verbosity, keyboard
        self.workdir = workdir
        self.config_path = workdir / "operator.toml"
        self.status_path = workdir / "operator-status.json"
        self.log_path = workdir / "operator.log"
        self.rule = policy("operator")
        dashboard = scene.operator.dashboard
        if args.dashboard:
            dashboard.enabled = True
        if dashboard.enabled:  # a restarted node serves the open pages on the same address
            if dashboard.port == 0:
                dashboard.port = free_loopback_ports(1)[0]
            if not dashboard.token and not os.environ.get(TOKEN_ENV):
                from common.web_token import new_token

                dashboard.token = new_token()
        # with the run's keys and the page's token: 0600, in our 0700 directory
        write_secret_file(self.config_path, config_toml(scene.operator, "operator", redact=False))

    def argv(self, n: int) -> list[str]:
        argv = [*self.verbosity, "operator", "--config", str(self.config_path)]
        argv += ["--status-file", str(self.status_path)]
        if self.keyboard:
            argv.append("--commands-from-stdin")
        if self.args.record:  # a restarted node records beside the crashed one's file
            name = "operator.mcap" if n == 0 else f"operator.restart{n}.mcap"
            argv += ["--record", str(self.args.record / name)]
            network = self.scene.network
            session = {  # what `deepxpalm export` puts in a dataset's metadata
                "scene": self.scene.scene.name,
                "network_scenario": network.scenario if network.enabled else "none",
            }
            for key, value in session.items():
                argv += ["--record-metadata", f"{key}={value}"]
        return argv

    def child(self) -> Child:
        rule = self.rule
        watchdog = None
        stop_post = None
        if rule is not None and rule.watchdog_sec > 0:
            watchdog = UnitWatchdog(
                self.workdir / "operator.notify", rule.watchdog_sec, rule.timeout_abort_sec
            )
        if (
            rule is not None
            and rule.stop_post
            and self.scene.operator.servos.get("kind") == ("feetech")
        ):
            lift = ["-v", *stop_post_args(rule.stop_post, self.config_path)]
            lift_log = self.workdir / "palm-lift.log"
            # at the unit's Nice=, as systemd runs every command of the unit
            stop_post = StopPost("operator", lambda: spawn_cli(lift, lift_log, "operator"))
        env = None if watchdog is None else watchdog.environ()
        stdin = subprocess.PIPE if self.keyboard else subprocess.DEVNULL
        return Child(
            "operator",
            lambda n: spawn_cli(self.argv(n), self.log_path, "operator", stdin=stdin, env=env),
            self.log_path,
            unit_restart_s("operator"),
            stop_post=stop_post,
            watchdog=watchdog,
        )

    @staticmethod
    def send(child: Child, action: str, kwargs: dict[str, Any]) -> None:
        """A key's command to the running node's stdin; dropped while it is down (as keys
        typed at a dead node's terminal are)."""
        proc = child.proc
        if proc is None or proc.stdin is None or proc.poll() is not None:
            return
        line = (json.dumps({"action": action, **kwargs}) + "\n").encode()
        try:
            fd = proc.stdin.fileno()
            os.set_blocking(fd, False)  # a node that stopped reading never stalls the demo
            os.write(fd, line)  # one line, under PIPE_BUF: written whole or not at all
        except BlockingIOError:
            log.warning("operator: not reading its commands; key %s dropped", action)
        except (BrokenPipeError, OSError, ValueError):
            pass  # it just died: the supervisor restarts it


def _configured(scenario_name: str) -> dict[str, Any]:
    """What the scenario says the operator should measure, to set beside what it did."""
    from common.netsim.scenario import load_scenario

    scenario = load_scenario(scenario_name)
    out: dict[str, Any] = {"mode": scenario.mode}
    for name in ("to_operator", "to_robot"):
        out[f"{name}_p50_ms"] = round(scenario.direction(name).delay_quantile_ms(0.5), 3)
    out["what"] = (
        "median one-way path delay per direction; the operator's link latency_p50_ms should "
        "match to_operator's, and clock_offset_ms be 0 (one machine) within its uncertainty"
    )
    return out


def demo_link_is_plain(args: argparse.Namespace, scene: Scene, use_netsim: bool) -> bool:
    """Whether the nodes talk plain TCP: only when asked with ``--plain``.

    By default the link is CURVE with keys made for the run, on loopback
    too: a plain loopback port takes commands from any local process (another
    user, a script, a browser extension's helper), and the page's token would
    not protect the arm. The link simulator's message mode re-publishes
    messages, so CURVE cannot pass it; that mode needs ``--plain``, said here
    rather than as a link that never comes up.
    """
    if args.plain:
        return True
    if use_netsim:
        from common.netsim.scenario import load_scenario

        mode = scene.network.mode or load_scenario(scene.network.scenario).mode
        if mode == "message":
            raise ConfigError(
                f"the link simulator's message mode (scenario {scene.network.scenario!r}, "
                "network.mode) re-publishes messages and cannot carry the demo's CURVE link: "
                "use network.mode = 'stream', or pass --plain (then any process on this "
                "machine can steer the arm)"
            )
    return False


def _use_fresh_curve_keys(scene: Scene, directory: Path) -> None:
    """Keys for this run only, in a directory only we can open: the robot allows just this
    operator's key, so a local process without it completes no handshake and commands nothing.
    """
    from common.security import SecurityConfig
    from deploy.keys_cli import allow, generate

    directory.mkdir(mode=0o700)
    directory.chmod(0o700)  # mkdir's mode passes through the umask
    robot_pub, robot_sec = generate(directory / "robot", "robot")
    op_pub, op_sec = generate(directory / "operator", "operator")
    authorized = directory / "authorized"
    allow(op_pub, authorized)
    scene.robot.link.security = SecurityConfig(
        mode="curve", secret_key_file=robot_sec, authorized_keys_dir=authorized
    )
    scene.operator.link.security = SecurityConfig(
        mode="curve", secret_key_file=op_sec, server_public_key_file=robot_pub
    )


def _summary(
    scene: Scene,
    status: live_view.OperatorStatus,
    elapsed: float,
    robot_path: Path,
    netsim_path: Path,
    errors: list[str],
) -> dict[str, Any]:
    """The run's figures; the operator's are its status file's last (its final counters,
    written as it stopped; those of its newest process when it was restarted)."""
    robot: dict[str, float] = {}
    if robot_path.exists():
        robot = json.loads(robot_path.read_text())
    else:
        errors.append("the robot node wrote no statistics")
    op = status.stats()
    if status.read() is None:
        errors.append("the operator node wrote no status")
    with_truth = int(op.get("stimuli_with_truth", 0))
    matching = int(op.get("stimuli_matching_truth", 0))
    out: dict[str, Any] = {
        "scene": scene.scene.name,
        "render_mode": scene.robot.render.mode,
        "network_scenario": scene.network.scenario if scene.network.enabled else None,
        "security": (
            "fabric (QUIC, mutual TLS, signed)"
            if scene.operator.link.mode == "fabric"
            else scene.operator.link.security.mode
        ),
        "duration_s": round(elapsed, 3),
        "frames_captured": int(robot.get("frames_captured", 0)),
        "frames_processed": int(robot.get("frames_processed", 0)),
        "frames_skipped_no_contact": int(robot.get("frames_no_contact", 0)),
        "frames_skipped_identical": int(robot.get("frames_identical", 0)),
        "inferences": int(robot.get("inferences", 0)),
        "stimuli_published": int(robot.get("stimuli_published", 0)),
        "keyframes_published": int(robot.get("keyframes", 0)),
        "stimuli_unchanged_not_sent": int(robot.get("stimuli_unchanged", 0)),
        "stimuli_received": int(op.get("stimuli_received", 0)),
        "servo_writes": int(op.get("servo_writes", 0)),
        "lift_offs": int(op.get("lift_offs", 0)),
        "latency_ms": {
            "p50": op.get("latency_p50_ms"),
            "p99": op.get("latency_p99_ms"),
            "p99.9": op.get("latency_p999_ms"),
            "max": op.get("latency_max_ms"),
            "samples": status.latency_samples(),
            "what": "frame capture (robot clock, offset-corrected) to servo command",
        },
        "pattern_match": {
            "share": (matching / with_truth) if with_truth else None,
            "matching": matching,
            "received_with_truth": with_truth,
            "what": "received stimuli pressing exactly the true pattern's cells",
        },
        "link": {k[5:]: v for k, v in op.items() if k.startswith("link_")},
        "rejected_messages": {
            "operator": int(op.get("decode_errors", 0)),
            "robot": int(robot.get("decode_errors", 0)),
        },
        "errors": errors,
    }
    if netsim_path.exists():
        out["netsim"] = json.loads(netsim_path.read_text())
    if scene.network.enabled:
        out["network_configured"] = _configured(scene.network.scenario)
    return out
