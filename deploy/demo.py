"""``deepxpalm demo``: both nodes, simulated devices and the link simulator, one command.

Every node runs as a child process, as it would on its own machine: the
robot node, the link simulator, the operator node (``deepxpalm operator``,
which writes what it shows to a status file), and the simulated servo bus
(``deepxpalm sim servos``) on a pty whose path survives its restarts. The
demo draws the live view from the operator's status file (or prints one JSON
summary with ``--json``) and hands the keys to the operator over its stdin.
Latency comes from the messages' timestamps.

The demo is four steps: the scene (its settings, keys and timing), the
units (``deploy/demo_units.py``: each process of the catalogue started once
the one before it said ``READY=1`` with what it bound), the supervision (a
child that dies is restarted as its systemd unit would be,
``deploy/units/supervisor.py``; the live view and the summary say so), and
the summary. The operator runs under its unit's rules: its watchdog ends a
frozen node, and after any end of the node ``deepxpalm palm lift`` opens the
servo bus and lifts the linkages off the palm before the node is started
again.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import json
import logging
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from common.config.typed import check_secret_file, from_dict
from common.errors import ConfigError
from common.process.command_line import add_overrides_argument, stop_on_signals
from common.process.sd_notify import Notifier
from common.wire.signing import write_secret_file
from deploy import live_view
from deploy.demo_units import DemoUnits
from deploy.scene import Scene, load_scene_dict, scene_path
from deploy.units.readiness import NotReady
from deploy.units.supervisor import Supervisor

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


def video_wanted(args: argparse.Namespace, scene: Scene) -> bool:
    """A camera for the dashboard or the recording, when the video extra is here."""
    if args.no_video or not (args.dashboard or scene.operator.dashboard.enabled or args.record):
        return False
    if importlib.util.find_spec("aiortc") is None:
        log.info("no camera: the video extra (aiortc) is not installed")
        return False
    return True


def run(args: argparse.Namespace) -> int:
    data = load_scene_dict(args.scene, args.overrides)
    scene: Scene = from_dict(Scene, data, where="")
    check_secret_file(scene_path(args.scene), scene)
    if args.scenario:
        scene.network.scenario = args.scenario
    use_netsim = scene.network.enabled and not args.no_netsim
    workdir = Path(tempfile.mkdtemp(prefix="deepxpalm-demo-"))
    if use_netsim:
        fit_command_timing(scene)
    fabric = None
    if args.fabric:
        from deploy.demo_fabric import use_fresh_fabric

        fabric = use_fresh_fabric(scene, workdir / "fabric")
    elif demo_link_is_plain(args, scene, use_netsim):
        scene.robot.link.allow_plain_commands = True
        log.warning(
            "--plain: the robot's command port%s takes commands from any process on this machine",
            " and the link simulator's" if use_netsim else "",
        )
    else:
        _use_fresh_curve_keys(scene, workdir / "keys")
    units = DemoUnits(
        args,
        scene,
        workdir,
        use_netsim=use_netsim,
        fabric=fabric,
        video=video_wanted(args, scene),
        verbosity=["-v"] if logging.getLogger().level <= logging.INFO else [],
    )
    children = Supervisor()
    errors: list[str] = []
    stop = stop_on_signals()
    status = live_view.OperatorStatus(workdir / "operator-status.json")
    t0 = time.monotonic()
    try:
        try:
            units.start(children, stop)  # each process ready before the next
            children.armed = not stop.is_set()  # up: from now on, restart
        except NotReady as e:  # a wrong setting, a missing device: its log's tail
            if not stop.is_set():  # Ctrl-C while it starts is no failure
                errors.append(str(e))
                log.error("%s", e)  # on stderr too: --json's reader may only keep the log
        operator = units.operator
        if children.armed:  # whoever started the demo (the soak, the bench) may count on it
            served = (
                {}
                if operator is None or operator.dashboard_base is None
                else {"dashboard": operator.dashboard_base}
            )
            Notifier().ready("every process ready", {"logs": str(workdir), **served})
        t0 = time.monotonic()  # --duration counts from the whole deployment being ready
        keyboard = live_view.Keyboard() if not args.json else contextlib.nullcontext()
        dashboard_line = ""
        if scene.operator.dashboard.enabled and children.armed and operator is not None:
            url = operator.dashboard_url
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
        children.stop_all(errors)
    summary = _summary(scene, status, ran_s, units.robot_stats, units.netsim_stats, errors)
    summary["processes"] = children.summary()
    summary["logs"] = str(workdir)
    print(json.dumps(summary, indent=2))
    return 1 if errors else 0


#: how often the demo's supervisor looks at its children: a dead operator's palm lift starts
#: within this, and a frozen one's watchdog is checked as often
SUPERVISE_PERIOD_S = 0.02
#: how often the live view is drawn (and the keys read)
VIEW_PERIOD_S = 0.05


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
    from common.keys.curve import SecurityConfig
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
