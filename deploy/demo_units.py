"""The demo's processes: its scene made into units of the catalogue, each ready before the next.

Every process is a ``deploy.units`` service under its unit's rules, started
in the order their addresses are needed, as systemd starts units ordered
``After=`` one another: the lab world (its addresses, for the robot's lab
devices and the lab camera), the video server (its address, for the robot's
link), the fabric's router (for the nodes), the robot node, the link
simulator (between the robot's endpoints, or the router's, and the
operator's), the servo bus simulator and the operator node. Each binds port
0 and says what it got in its ``READY=1``; nobody chooses a port for another
process. A restarted process binds the address its first one reported (the
demo writes it into the process's config), so its peers find it again.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import threading
from pathlib import Path
from typing import Any

from common.config.typed import config_toml, from_dict
from common.errors import ConfigError
from common.web.web_token import new_token, with_token
from common.wire.signing import write_secret_file
from deploy.demo_fabric import DemoFabric
from deploy.scene import Scene
from deploy.units.catalogue import unit
from deploy.units.child import Child, StopPost
from deploy.units.readiness import Ready
from deploy.units.service import Service
from deploy.units.supervisor import Supervisor
from operator_side.dashboard.config import TOKEN_ENV, VIDEO_OVER_LINK

#: a TCP endpoint on loopback whose port the process chooses (and reports)
ANY_TCP = "tcp://127.0.0.1:0"
LAB_DEVICES = ("tactile", "gripper", "arm")


class DemoUnits:
    """The scene's processes; :meth:`start` adds each to the supervisor once the one before
    it is ready."""

    def __init__(
        self,
        args: argparse.Namespace,
        scene: Scene,
        workdir: Path,
        *,
        use_netsim: bool,
        fabric: DemoFabric | None,
        video: bool,
        verbosity: list[str],
    ) -> None:
        self.args, self.scene, self.workdir = args, scene, workdir
        self.use_netsim, self.fabric, self.video = use_netsim, fabric, video
        self.verbosity = verbosity
        self.robot_config = workdir / "robot.toml"
        self.robot_stats = workdir / "robot-stats.json"
        self.netsim_stats = workdir / "netsim-stats.json"
        self.operator: OperatorChild | None = None
        self.world_addresses: Path | None = None

    def start(self, children: Supervisor, stop: threading.Event) -> None:
        """Every process started and ready, in order (``NotReady`` names the one that failed)."""
        for make in (self._world, self._video, self._router, self._robot, self._netsim):
            child = make()
            if child is not None:
                children.add(child, stop_event=stop)
        servos = servo_simulator(self.scene, self.workdir)
        if servos is not None:
            # a bus that came back is opened again by a new node (its pty is a new one)
            children.add(Child(servos, restarts_too=("operator",)), stop_event=stop)
        self.operator = OperatorChild(
            self.args, self.scene, self.workdir, self.verbosity, keyboard=not self.args.json
        )
        children.add(self.operator.child(), stop_event=stop)

    def _service(self, name: str, argv: Any, **kw: Any) -> Service:
        return Service(name, argv, self.workdir / f"{name}.log", **kw)

    # ------------------------------------------------------------ the lab world
    def _world(self) -> Child | None:
        """The simulated lab as its own process, when the scene's devices live in one: its
        READY=1's addresses, written where the robot's lab devices (``running_world``) and
        the video server's lab camera read them. None when no device is a lab kind, or one
        already names a running world."""
        sections = [getattr(self.scene.robot, d) for d in LAB_DEVICES]
        lab = [s for s in sections if s.get("kind") == "lab"]
        if not lab or any(s.get("running_world") for s in lab):
            return None
        configs = {str(s["world_config"]) for s in lab if s.get("world_config")}
        if len(configs) > 1:
            raise ConfigError(f"the scene's lab devices name different worlds: {sorted(configs)}")
        addresses = self.world_addresses = self.workdir / "world.json"
        for section in lab:
            section["running_world"] = str(addresses)
        argv = ["sim", "world", *(["--config", configs.pop()] if configs else [])]

        def written(ready: Ready) -> None:  # whole or not at all
            partial = addresses.with_suffix(".partial")
            partial.write_text(json.dumps(ready.endpoints))
            partial.replace(addresses)

        # a restarted world listens on new ports: the robot and the camera follow it
        return Child(
            self._service("world", argv), restarts_too=("robot", "video"), after_ready=written
        )

    # ------------------------------------------------------------ the camera
    def _video(self) -> Child | None:
        """``deepxpalm video``: the lab's camera, or the test pattern, on a port of its own;
        the robot offers it to viewers through its link (its READY=1's address)."""
        if not self.video:
            return None
        scene = self.scene
        token_file = self.workdir / "video.token"
        settings = video_settings(
            self.world_addresses,
            token_file,
            scene.network.scenario if self.use_netsim else "",
            scene.network.seed,
        )
        port = [0]  # its first process's, bound again by a restart

        def argv(n: int) -> list[str]:
            sets = [*settings, f"port={port[0]}"]
            if self.args.record:  # the camera beside the robot's recording, a restart's beside
                name = "camera.mcap" if n == 0 else f"camera.restart{n}.mcap"
                sets.append(f'record="{self.args.record / name}"')
            return ["-v", "video", *(a for s in sets for a in ("--set", s))]

        def serving(ready: Ready) -> None:
            url = ready.endpoints["signalling"]
            port[0] = int(url.rstrip("/").rpartition(":")[2])
            scene.robot.link.video_url = url  # offers reach it through the robot's link
            scene.robot.link.video_token_file = token_file
            scene.operator.dashboard.video_url = VIDEO_OVER_LINK

        # -v: it says when the camera opens and closes; the demo runs on without a camera
        return Child(self._service("video", argv), essential=False, after_ready=serving)

    # ------------------------------------------------------------ the fabric's router
    def _router(self) -> Child | None:
        fabric = self.fabric
        if fabric is None:
            return None
        argv = [*self.verbosity, "router", "--config", str(fabric.router_config)]

        def listening(ready: Ready) -> None:
            fabric.router_up(self.scene, ready.endpoints["listen"], self.use_netsim)

        return Child(self._service("router", argv), after_ready=listening)

    # ------------------------------------------------------------ the robot node
    def _robot(self) -> Child:
        link = self.scene.robot.link
        if link.mode != "fabric":
            link.telemetry_endpoint = link.command_endpoint = ANY_TCP
        self._write_robot_config()

        def argv(n: int) -> list[str]:
            args = [*self.verbosity, "robot", "--config", str(self.robot_config)]
            args += ["--stats-file", str(self.robot_stats)]
            if self.args.record:  # a restarted node records beside the crashed one's file
                name = "robot.mcap" if n == 0 else f"robot.restart{n}.mcap"
                args += ["--record", str(self.args.record / name)]
            return args

        def bound(ready: Ready) -> None:
            if link.mode == "fabric":
                return  # it connects to the router: nothing of its own to report
            link.telemetry_endpoint = ready.endpoints["telemetry"]
            link.command_endpoint = ready.endpoints["commands"]
            self._write_robot_config()  # a restarted node binds the same ports
            if not self.use_netsim:
                op = self.scene.operator.link
                op.telemetry_endpoint = link.telemetry_endpoint
                op.command_endpoint = link.command_endpoint

        return Child(self._service("robot", argv), after_ready=bound)

    def _write_robot_config(self) -> None:
        # with the run's keys: in our 0700 directory
        self.robot_config.write_text(config_toml(self.scene.robot, "robot", redact=False))

    # ------------------------------------------------------------ the link simulator
    def _netsim(self) -> Child | None:
        """``deepxpalm netsim`` between the robot's endpoints (or the router's UDP address)
        and ports of its own for the operator, which its READY=1 names."""
        if not self.use_netsim:
            return None
        net = self.scene.network
        robot = self.scene.robot.link
        fixed = [*self.verbosity, "netsim", "--scenario", net.scenario, "--seed", str(net.seed)]
        if self.fabric is not None:
            fixed += ["--mode", "datagram", "--robot-telemetry", self.fabric.router_udp]
            sides = {"--operator-telemetry": "udp://127.0.0.1:0"}
        else:
            fixed += ["--mode", net.mode] if net.mode else []
            fixed += ["--robot-telemetry", robot.telemetry_endpoint]
            fixed += ["--robot-commands", robot.command_endpoint]
            sides = {"--operator-telemetry": ANY_TCP, "--operator-commands": ANY_TCP}
        fixed += ["--stats-file", str(self.netsim_stats)]

        def argv(_n: int) -> list[str]:
            return [*fixed, *(a for kv in sides.items() for a in kv)]

        def bound(ready: Ready) -> None:
            ends = ready.endpoints
            op = self.scene.operator.link
            if self.fabric is not None:
                sides["--operator-telemetry"] = ends["operator_telemetry"]
                op.fabric.router_endpoint = "quic/" + ends["operator_telemetry"][len("udp://") :]
                return
            sides["--operator-telemetry"] = op.telemetry_endpoint = ends["operator_telemetry"]
            sides["--operator-commands"] = op.command_endpoint = ends["operator_commands"]

        return Child(self._service("netsim", argv), after_ready=bound)


def video_settings(
    world_addresses: Path | None, token_file: Path, scenario: str = "", seed: int = 0
) -> list[str]:
    """``deepxpalm video``'s settings but its port: the lab's camera, or the test pattern.

    Its signalling secret is in ``token_file`` (the robot node reads it there, so the
    secret never appears on a command line); its media stays on loopback, and crosses
    the link simulator's datagram mode under ``scenario`` when there is one.
    """
    settings = [f'token_file="{token_file}"', 'media_interfaces=["lo"]']
    if scenario:
        settings += [f'link_scenario="{scenario}"', f"link_seed={seed}"]
    if world_addresses is not None:
        settings += ['source="lab"', f'lab.addresses_file="{world_addresses}"']
    else:
        settings += ["test_pattern.width=320", "test_pattern.height=240", "test_pattern.fps=15"]
    return settings


def servo_simulator(scene: Scene, workdir: Path) -> Service | None:
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
    argv = ["sim", "servos", "--config", str(config), "--status-file", str(status)]
    return Service("sim-servos", argv, workdir / "servos.log", name="servos")


class OperatorChild:
    """``deepxpalm operator`` as the demo's child, under its unit's rules.

    Its config (the scene's operator with the run's keys and the endpoints its
    peers reported) is a 0600 file in the demo's directory; it writes its live
    view and counters to ``operator-status.json``; the keys reach it as JSON
    lines on its stdin. It runs with its unit's watchdog (on its notify
    socket) and, when its servos are a bus of their own, its unit's
    ``ExecStopPost=`` (``deepxpalm palm lift``) after every end. Its dashboard
    binds a free port, reported in its READY=1 and kept by a restarted node,
    so an open page finds it again.
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
        self.dashboard_url: str | None = None  # with its token, once the node said where
        self.dashboard_base: str | None = None  # without it
        dashboard = scene.operator.dashboard
        if args.dashboard:
            dashboard.enabled = True
        if dashboard.enabled and not dashboard.token and not os.environ.get(TOKEN_ENV):
            dashboard.token = new_token()
        self._write_config()

    def _write_config(self) -> None:
        # with the run's keys and the page's token: 0600, in our 0700 directory
        write_secret_file(
            self.config_path, config_toml(self.scene.operator, "operator", redact=False)
        )

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

    def _serving(self, ready: Ready) -> None:
        """Its dashboard's address: kept for a restarted node, shown with its token."""
        base = ready.endpoints.get("dashboard")
        dashboard = self.scene.operator.dashboard
        if base is None or not dashboard.enabled:
            return
        port = int(base.rstrip("/").rpartition(":")[2])
        if dashboard.port != port:
            dashboard.port = port
            self._write_config()
        self.dashboard_base = base
        self.dashboard_url = with_token(base, dashboard.token or os.environ[TOKEN_ENV])

    def child(self) -> Child:
        spec = unit("operator")
        stop_post = None
        if self.scene.operator.servos.get("kind") == "feetech":
            stop_post = StopPost.of(spec, self.config_path, self.workdir / "palm-lift.log")
        stdin = subprocess.PIPE if self.keyboard else subprocess.DEVNULL
        service = Service(spec, self.argv, self.log_path, stdin=stdin)
        return Child(service, stop_post=stop_post, after_ready=self._serving)

    @staticmethod
    def send(child: Child, action: str, kwargs: dict[str, Any]) -> None:
        """A key's command to the running node's stdin; dropped while it is down (as keys
        typed at a dead node's terminal are)."""
        import logging

        proc = child.proc
        if proc is None or proc.stdin is None or proc.poll() is not None:
            return
        line = (json.dumps({"action": action, **kwargs}) + "\n").encode()
        try:
            fd = proc.stdin.fileno()
            os.set_blocking(fd, False)  # a node that stopped reading never stalls the demo
            os.write(fd, line)  # one line, under PIPE_BUF: written whole or not at all
        except BlockingIOError:
            logging.getLogger(__name__).warning(
                "operator: not reading its commands; key %s dropped", action
            )
        except (BrokenPipeError, OSError, ValueError):
            pass  # it just died: the supervisor restarts it
