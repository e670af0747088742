"""A relay or router, robots and operators as real processes on this machine (tests, bench).

``transport="relay"``: the ZeroMQ relay, every hop CURVE. ``transport="fabric"``: a
Zenoh router made from the roster (``deepxpalm router``), every hop QUIC with
the members' certificates. Either way every operator signs, and one roster says who is who:
the same layout as three machines (docs/deploy.md), on 127.0.0.1 with free
ports. ``Fleet`` writes the keys, the roster and each process's config into
one work folder, starts the processes and stops them all.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import subprocess
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import zmq.auth

from common import web_token
from common.roster import operator_entry, robot_entry
from common.signing import generate_key_files, load_public_key, write_secret_file
from common.transport import free_loopback_ports
from deploy.keys_cli import generate
from harness.processes import spawn_cli, stop

log = logging.getLogger(__name__)

_ROBOT_TOML = """
[robot]
publish_rate_hz = {rate}
{devices}
[robot.arm]
{arm}
[robot.link]
mode = "relay"
robot_name = "{name}"
roster_file = "{roster}"
telemetry_endpoint = "{tel}"
command_endpoint = "{cmd}"
frame_display_rate_hz = {frames}
video_url = "{video_url}"
signing_key_file = "{signing}"
[robot.link.security]
mode = "curve"
secret_key_file = "{secret}"
server_public_key_file = "{relay_public}"
"""

#: the tactile source and renderer of a robot with no devices of its own: a grasp held for an hour
SCRIPTED_TACTILE = """
[robot.render]
mode = "mask_ground_truth"
deadband_n = 0.0
[robot.tactile]
kind = "scripted"
[robot.tactile.script]
loop = false
grasps = [{pattern = 6, grip_level = 25, ramp_s = 0.1, hold_s = 3600.0}]
"""

_OPERATOR_TOML = """
[operator]
[operator.servos]
{servos}
[operator.link]
robot_name = "{robot}"
signing_key_file = "{signing}"
robot_key_file = "{robot_key}"
telemetry_endpoint = "{tel}"
command_endpoint = "{cmd}"
want_frames = {frames}
request_control = {request}
[operator.link.security]
mode = "curve"
secret_key_file = "{secret}"
server_public_key_file = "{relay_public}"
"""

_ROBOT_FABRIC_TOML = """
[robot.link]
mode = "fabric"
robot_name = "{name}"
roster_file = "{roster}"
frame_display_rate_hz = {frames}
video_url = "{video_url}"
signing_key_file = "{signing}"
[robot.link.fabric]
router_endpoint = "{router}"
cert_dir = "{cert_dir}"
"""

_OPERATOR_FABRIC_TOML = """
[operator]
[operator.servos]
{servos}
[operator.link]
mode = "fabric"
robot_name = "{robot}"
signing_key_file = "{signing}"
robot_key_file = "{robot_key}"
want_frames = {frames}
request_control = {request}
[operator.link.fabric]
router_endpoint = "{router}"
cert_dir = "{cert_dir}"
name = "{name}"
"""

_ROUTER_TOML = """
[router]
listen_endpoint = "quic/127.0.0.1:{port}"
roster_file = "{roster}"
cert_dir = "{cert_dir}"
status_file = "{status}"
"""

_RELAY_TOML = """
[relay]
robots_telemetry_endpoint = "tcp://127.0.0.1:{p0}"
robots_command_endpoint = "tcp://127.0.0.1:{p1}"
operators_telemetry_endpoint = "tcp://127.0.0.1:{p2}"
operators_command_endpoint = "tcp://127.0.0.1:{p3}"
roster_file = "{roster}"
roster_status_file = "{status}"
stats_interval_s = 0
[relay.security]
mode = "curve"
secret_key_file = "{secret}"
"""


@dataclass
class Member:
    """One person (an operator key) or robot in the roster."""

    name: str
    role: str  # controller, observer, recorder, or robot
    curve_public: Path
    curve_secret: Path
    signing_secret: Path | None = None
    signing_public: bytes | None = None


@dataclass
class Proc:
    name: str
    popen: subprocess.Popen
    log_path: Path
    stats_path: Path
    stdin: IO[str] | None = None

    def send(self, command: dict[str, Any]) -> None:
        """One JSON command line to an operator started with ``--commands-from-stdin``."""
        self.stdin.write(json.dumps(command) + "\n")
        self.stdin.flush()

    def stats(self) -> dict[str, float]:
        return json.loads(self.stats_path.read_text()) if self.stats_path.exists() else {}

    def log_text(self) -> str:
        return self.log_path.read_text() if self.log_path.exists() else ""


@dataclass
class Fleet:
    """Keys, roster and processes under ``workdir``; a context manager that stops everything."""

    robots: list[str]
    operators: dict[str, str]  # name -> role
    workdir: Path = field(default_factory=lambda: Path(tempfile.mkdtemp(prefix="deepxpalm-fleet-")))
    #: relay's roster, if it should differ from the robots' (a compromised-relay trial)
    relay_roles: dict[str, str] | None = None
    members: dict[str, Member] = field(default_factory=dict)
    procs: dict[str, Proc] = field(default_factory=dict)
    env: dict[str, str] = field(default_factory=lambda: {**os.environ, "PYTHONUNBUFFERED": "1"})
    #: relay name -> its four endpoints, for every relay started
    relay_endpoints: dict[str, dict[str, str]] = field(default_factory=dict)
    #: observers whose roster entry says ``video = true`` (video is a controller's otherwise)
    video_observers: frozenset[str] = frozenset()
    #: "relay" (ZeroMQ, CURVE) or "fabric" (a Zenoh router, QUIC and certificates)
    transport: str = "relay"

    def __post_init__(self) -> None:
        keys = self.workdir / "keys"
        pub, sec = generate(keys, "relay")
        self.members["relay"] = Member("relay", "relay", pub, sec)
        for name in self.robots:  # a robot signs its stream: a relay cannot forge a palm
            pub, sec = generate(keys, f"robot-{name}")
            spub, ssec = generate_key_files(keys, f"robot-{name}")
            self.members[name] = Member(name, "robot", pub, sec, ssec, load_public_key(spub))
        everyone = {**(self.relay_roles or {}), **self.operators}
        for name, role in everyone.items():
            self.add_member(name, role)
        self.roster = self._write_roster("roster.toml", self.operators)
        self.relay_roster = (
            self.roster
            if self.relay_roles is None
            else self._write_roster("relay-roster.toml", self.relay_roles)
        )
        if self.transport == "fabric":
            from deploy.keys_cli import fabric_certificates

            self.cert_dir = self.workdir / "fabric"
            fabric_certificates(self.roster, self.cert_dir, "router", ("127.0.0.1",), False)
            self.router_port = free_loopback_ports(1, udp=True)[0]
            self.router_endpoint = f"quic/127.0.0.1:{self.router_port}"
        ports = free_loopback_ports(4)
        self.robots_telemetry, self.robots_command, self.ops_telemetry, self.ops_command = (
            f"tcp://127.0.0.1:{p}" for p in ports
        )
        self._ports = ports

    def add_member(self, name: str, role: str) -> Member:
        """Keys for a person not (yet) in the roster: ``rewrite_roster`` lets them in."""
        keys = self.workdir / "keys"
        pub, sec = generate(keys, name)
        spub, ssec = generate_key_files(keys, name)
        self.members[name] = Member(name, role, pub, sec, ssec, load_public_key(spub))
        if getattr(self, "cert_dir", None) is not None:  # the fabric's CA is made: one more
            from common.fabric.certificates import CertFiles, issue

            issue(CertFiles.in_dir(self.cert_dir, "ca"), self.cert_dir, name)
        return self.members[name]

    def rewrite_roster(self, roles: dict[str, str]) -> None:
        """The shared roster now lists ``roles`` (name -> role); SIGHUP makes them read it."""
        if self.relay_roster != self.roster:
            raise ValueError("this fleet's relay has a roster of its own")
        self.operators = dict(roles)
        tmp = self._write_roster("roster.toml.new", roles)
        tmp.replace(self.roster)  # atomic: a reload never reads half a file

    def _write_roster(self, filename: str, roles: dict[str, str]) -> Path:
        entries = []
        for name, role in roles.items():
            m = self.members[name]
            curve, _ = zmq.auth.load_certificate(m.curve_public)
            video = True if name in self.video_observers else None
            entries.append(operator_entry(name, role, curve, m.signing_public, video))
        for name in self.robots:  # last, as docs/deploy.md says: a cut file loses every robot
            curve, _ = zmq.auth.load_certificate(self.members[name].curve_public)
            entries.append(robot_entry(name, curve))
        path = self.workdir / filename
        path.write_text("\n".join(entries))
        return path

    def client_security(self, name: str) -> dict[str, str]:
        """A member's CURVE client settings toward the relay, as SecurityConfig keys."""
        return {
            "mode": "curve",
            "secret_key_file": str(self.members[name].curve_secret),
            "server_public_key_file": str(self.members["relay"].curve_public),
        }

    def signing_key(self, name: str) -> bytes:
        return self.members[name].signing_public

    # ------------------------------------------------------------ processes
    def _start(self, name: str, args: list[str], stdin: bool = False) -> Proc:
        """``deepxpalm ARGS`` at the priority its systemd unit gives it (``args[1]``: the unit)."""
        log_path = self.workdir / f"{name}.log"
        stats_path = self.workdir / f"{name}-stats.json"
        with log_path.open("w") as out:
            popen = spawn_cli(
                [*args, "--stats-file", str(stats_path)],
                out,
                unit=args[1],
                stdin=subprocess.PIPE if stdin else subprocess.DEVNULL,
                env=self.env,
                text=True,
            )
        proc = Proc(name, popen, log_path, stats_path, popen.stdin if stdin else None)
        self.procs[name] = proc
        return proc

    def start_router(self, name: str = "router") -> Proc:
        """The fabric's Zenoh router, its access control made from the roster."""
        config = self.workdir / f"{name}.toml"
        write_secret_file(
            config,
            _ROUTER_TOML.format(
                port=self.router_port,
                roster=self.roster,
                cert_dir=self.cert_dir,
                status=self.workdir / f"{name}-status.json",
            ),
        )
        return self._start(name, ["-v", "router", "--config", str(config)])

    def start_hub(self) -> Proc:
        """What the fleet's members meet through: the relay or the router."""
        return self.start_router() if self.transport == "fabric" else self.start_relay()

    def start_relay(self, name: str = "relay") -> Proc:
        """The relay; another ``name`` starts a second one on fresh ports (``relay_endpoints``)."""
        p = self._ports if name == "relay" else free_loopback_ports(4)
        self.relay_endpoints[name] = {
            "robots_telemetry": f"tcp://127.0.0.1:{p[0]}",
            "robots_command": f"tcp://127.0.0.1:{p[1]}",
            "operators_telemetry": f"tcp://127.0.0.1:{p[2]}",
            "operators_command": f"tcp://127.0.0.1:{p[3]}",
        }
        config = self.workdir / f"{name}.toml"
        write_secret_file(
            config,
            _RELAY_TOML.format(
                p0=p[0],
                p1=p[1],
                p2=p[2],
                p3=p[3],
                roster=self.relay_roster,
                status=self.workdir / f"{name}-roster-status.json",
                secret=self.members["relay"].curve_secret,
            ),
        )
        return self._start(name, ["-v", "relay", "--config", str(config)])

    def robot_config(
        self,
        name: str,
        arm_host: str | None,
        rate_hz: float = 60.0,
        video_url: str = "",
        devices: str = SCRIPTED_TACTILE,
    ) -> Path:
        """Write robot ``name``'s config (relay mode, CURVE, the roster); its path.

        ``video_url``: a video server on this machine that viewers reach through the relay.
        ``devices``: TOML of every robot section but the arm and the link (the renderer,
        the tactile source, a gripper); by default a scripted grasp and no gripper.
        """
        arm = f'kind = "ur_rtde"\nhost = "{arm_host}"' if arm_host else 'kind = "none"'
        config = self.workdir / f"{name}.toml"
        if self.transport == "fabric":
            head, _, _ = _ROBOT_TOML.partition("[robot.link]")
            text = head.format(rate=rate_hz, arm=arm, devices=devices) + _ROBOT_FABRIC_TOML.format(
                name=name,
                roster=self.roster,
                frames=15.0,
                video_url=video_url,
                signing=self.members[name].signing_secret,
                router=self.router_endpoint,
                cert_dir=self.cert_dir,
            )
            write_secret_file(config, text)
            return config
        write_secret_file(
            config,
            _ROBOT_TOML.format(
                rate=rate_hz,
                arm=arm,
                name=name,
                roster=self.roster,
                tel=self.robots_telemetry,
                cmd=self.robots_command,
                frames=15.0,
                secret=self.members[name].curve_secret,
                relay_public=self.members["relay"].curve_public,
                video_url=video_url,
                signing=self.members[name].signing_secret,
                devices=devices,
            ),
        )
        return config

    def start_robot(
        self,
        name: str,
        arm_host: str | None,
        rate_hz: float = 60.0,
        video_url: str = "",
        devices: str = SCRIPTED_TACTILE,
    ) -> Proc:
        config = self.robot_config(name, arm_host, rate_hz, video_url, devices)
        return self._start(name, ["-v", "robot", "--config", str(config)])

    def start_video(
        self,
        name: str = "video",
        fps: float = 15.0,
        port: int | None = None,
        settings: tuple[str, ...] = (),
    ) -> tuple[Proc, str]:
        """A video server (the stamped test pattern, 320x240) on loopback; (process, its URL,
        token included: a robot's link.video_url).

        ``port``: the one it had before a restart (default: a free one). Its token file
        stays in the workdir, so a restarted server keeps its token. ``settings``: more
        ``--set`` overrides (``ice_timeout_s=3``)."""
        port = port or free_loopback_ports(1)[0]
        url = self.video_url(name, port)
        settings = (*settings, f"port={port}", "test_pattern.width=320", "test_pattern.height=240")
        settings += (f"test_pattern.fps={fps}", f'token_file="{self.workdir / name}.token"')
        args = ["-v", "video", *(a for s in settings for a in ("--set", s))]
        return self._start(name, args), url

    def video_url(self, name: str, port: int) -> str:
        """Video server ``name``'s URL on ``port``, with the token of its file in the workdir."""
        token = web_token.token_file(self.workdir / f"{name}.token", "video token_file")
        return web_token.with_token(f"ws://127.0.0.1:{port}/", token)

    def start_operator(
        self,
        name: str,
        robot: str,
        *,
        request_control: bool = False,
        want_frames: bool = True,
        extra: list[str] | None = None,
        servos: str = 'kind = "recording"',
        endpoints: tuple[str, str] | None = None,
    ) -> Proc:
        """An operator process; ``servos`` is its ``[operator.servos]`` TOML body, and
        ``endpoints`` (telemetry, commands) another path to the relay (a link simulator)."""
        m = self.members[name]
        tel, cmd = endpoints or (self.ops_telemetry, self.ops_command)
        proc_name = f"{name}@{robot}"  # one key may follow several robots, a process each
        config = self.workdir / f"{proc_name}.toml"
        if self.transport == "fabric" and endpoints is None:
            write_secret_file(
                config,
                _OPERATOR_FABRIC_TOML.format(
                    robot=robot,
                    signing=m.signing_secret,
                    robot_key=self.workdir / "keys" / f"robot-{robot}.sign",
                    frames=str(want_frames).lower(),
                    servos=servos,
                    request=str(request_control).lower(),
                    router=self.router_endpoint,
                    cert_dir=self.cert_dir,
                    name=name,
                ),
            )
            args = ["-v", "operator", "--config", str(config), "--commands-from-stdin"]
            return self._start(proc_name, [*args, *(extra or [])], stdin=True)
        write_secret_file(
            config,
            _OPERATOR_TOML.format(
                robot=robot,
                signing=m.signing_secret,
                robot_key=self.workdir / "keys" / f"robot-{robot}.sign",
                tel=tel,
                cmd=cmd,
                frames=str(want_frames).lower(),
                servos=servos,
                request=str(request_control).lower(),
                secret=m.curve_secret,
                relay_public=self.members["relay"].curve_public,
            ),
        )
        args = ["-v", "operator", "--config", str(config), "--commands-from-stdin"]
        return self._start(proc_name, [*args, *(extra or [])], stdin=True)

    def start_recorder(self, name: str, output: Path | None = None) -> Proc:
        m = self.members[name]
        config = self.workdir / f"{name}.toml"
        if self.transport == "fabric":
            lines = [
                "[recorder]",
                'mode = "fabric"',
                f"robots = [{', '.join(repr(r).replace(chr(39), chr(34)) for r in self.robots)}]",
                *([f'output = "{output}"'] if output is not None else []),
                "[recorder.fabric]",
                f'router_endpoint = "{self.router_endpoint}"',
                f'cert_dir = "{self.cert_dir}"',
                f'name = "{name}"',
            ]
            write_secret_file(config, "\n".join(lines) + "\n")
            return self._start(name, ["-v", "record", "--config", str(config)])
        lines = [
            "[recorder]",
            f'telemetry_endpoint = "{self.ops_telemetry}"',
            f"robots = [{', '.join(repr(r).replace(chr(39), chr(34)) for r in self.robots)}]",
        ]
        if output is not None:
            lines.append(f'output = "{output}"')
        lines += [
            "[recorder.security]",
            'mode = "curve"',
            f'secret_key_file = "{m.curve_secret}"',
            f'server_public_key_file = "{self.members["relay"].curve_public}"',
        ]
        write_secret_file(config, "\n".join(lines) + "\n")
        return self._start(name, ["-v", "record", "--config", str(config)])

    def wait_for(self, cond: Callable[[], bool], timeout_s: float, what: str) -> None:
        """Poll ``cond`` until true; else fail naming ``what``, with every process's log tail."""
        deadline = time.monotonic() + timeout_s
        while not cond():
            if time.monotonic() > deadline:
                logs = "\n".join(f"--- {n}\n{p.log_text()[-3000:]}" for n, p in self.procs.items())
                raise AssertionError(f"timed out waiting for {what}\n{logs}")
            time.sleep(0.05)

    def stop(self, name: str, sig: int | None = None, timeout_s: float = 15.0) -> int:
        """``sig`` (default: what ``systemctl stop`` sends), then a kill; the exit code."""
        popen = self.procs[name].popen
        if sig is None:
            stop(popen, timeout_s)
        else:
            stop(popen, timeout_s, sig)
        return popen.returncode

    def close(self) -> None:
        for name in reversed(list(self.procs)):  # operators first, the relay last
            self.stop(name)
            stdin = self.procs[name].stdin
            if stdin is not None and not stdin.closed:
                with contextlib.suppress(BrokenPipeError):
                    stdin.close()

    def __enter__(self) -> Fleet:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
