"""A router, robots and operators as real processes on this machine (tests, bench).

The fabric across sites: a Zenoh router made from the roster (``deepxpalm
router``), every hop QUIC with the members' certificates; every operator
signs, every robot signs its stream, and one roster says who is who:
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
    """Keys, certificates, roster and processes under ``workdir``; a context manager that
    stops everything."""

    robots: list[str]
    operators: dict[str, str]  # name -> role
    workdir: Path = field(default_factory=lambda: Path(tempfile.mkdtemp(prefix="deepxpalm-fleet-")))
    #: the router's roster, if it should differ from the robots' (a compromised-router trial:
    #: the robots still judge every command by their own roster)
    router_roles: dict[str, str] | None = None
    members: dict[str, Member] = field(default_factory=dict)
    procs: dict[str, Proc] = field(default_factory=dict)
    env: dict[str, str] = field(default_factory=lambda: {**os.environ, "PYTHONUNBUFFERED": "1"})
    #: observers whose roster entry says ``video = true`` (video is a controller's otherwise)
    video_observers: frozenset[str] = frozenset()

    def __post_init__(self) -> None:
        from deploy.keys_cli import fabric_certificates

        keys = self.workdir / "keys"
        for name in self.robots:  # a robot signs its stream: a router cannot forge a palm
            pub, sec = generate(keys, f"robot-{name}")
            spub, ssec = generate_key_files(keys, f"robot-{name}")
            self.members[name] = Member(name, "robot", pub, sec, ssec, load_public_key(spub))
        everyone = {**(self.router_roles or {}), **self.operators}
        for name, role in everyone.items():
            self._keys(name, role)
        self.roster = self._write_roster("roster.toml", self.operators)
        self.router_roster = (
            self.roster
            if self.router_roles is None
            else self._write_roster("router-roster.toml", self.router_roles)
        )
        self.cert_dir = self.workdir / "fabric"
        fabric_certificates(self.router_roster, self.cert_dir, "router", ("127.0.0.1",), False)
        for name in set(self.operators) - set(self.router_roles or self.operators):
            self._certificate(name)  # in the robots' roster only: a certificate all the same
        self.router_port = free_loopback_ports(1, udp=True)[0]
        self.router_endpoint = f"quic/127.0.0.1:{self.router_port}"

    def _keys(self, name: str, role: str) -> Member:
        keys = self.workdir / "keys"
        pub, sec = generate(keys, name)
        spub, ssec = generate_key_files(keys, name)
        self.members[name] = Member(name, role, pub, sec, ssec, load_public_key(spub))
        return self.members[name]

    def _certificate(self, name: str) -> None:
        from common.fabric.certificates import CertFiles, issue

        issue(CertFiles.in_dir(self.cert_dir, "ca"), self.cert_dir, name)

    def add_member(self, name: str, role: str) -> Member:
        """Keys and a certificate for a person not (yet) in the roster: ``rewrite_roster``
        lets them in."""
        member = self._keys(name, role)
        self._certificate(name)
        return member

    def rewrite_roster(self, roles: dict[str, str]) -> None:
        """The shared roster now lists ``roles`` (name -> role); SIGHUP makes them read it."""
        if self.router_roster != self.roster:
            raise ValueError("this fleet's router has a roster of its own")
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
        """The fabric's Zenoh router, its access control made from the (router's) roster."""
        config = self.workdir / f"{name}.toml"
        write_secret_file(
            config,
            _ROUTER_TOML.format(
                port=self.router_port,
                roster=self.router_roster,
                cert_dir=self.cert_dir,
                status=self.workdir / f"{name}-status.json",
            ),
        )
        return self._start(name, ["-v", "router", "--config", str(config)])

    def robot_config(
        self,
        name: str,
        arm_host: str | None,
        rate_hz: float = 60.0,
        video_url: str = "",
        devices: str = SCRIPTED_TACTILE,
    ) -> Path:
        """Write robot ``name``'s config (the fabric, its certificate, the roster); its path.

        ``video_url``: a video server on this machine that viewers reach through the router.
        ``devices``: TOML of every robot section but the arm and the link (the renderer,
        the tactile source, a gripper); by default a scripted grasp and no gripper.
        """
        arm = f'kind = "ur_rtde"\nhost = "{arm_host}"' if arm_host else 'kind = "none"'
        config = self.workdir / f"{name}.toml"
        text = _ROBOT_TOML.format(
            rate=rate_hz, arm=arm, devices=devices
        ) + _ROBOT_FABRIC_TOML.format(
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
        router_endpoint: str | None = None,
    ) -> Proc:
        """An operator process; ``servos`` is its ``[operator.servos]`` TOML body, and
        ``router_endpoint`` another path to the router (a link simulator's datagram port)."""
        m = self.members[name]
        proc_name = f"{name}@{robot}"  # one key may follow several robots, a process each
        config = self.workdir / f"{proc_name}.toml"
        write_secret_file(
            config,
            _OPERATOR_FABRIC_TOML.format(
                robot=robot,
                signing=m.signing_secret,
                robot_key=self.workdir / "keys" / f"robot-{robot}.sign",
                frames=str(want_frames).lower(),
                servos=servos,
                request=str(request_control).lower(),
                router=router_endpoint or self.router_endpoint,
                cert_dir=self.cert_dir,
                name=name,
            ),
        )
        args = ["-v", "operator", "--config", str(config), "--commands-from-stdin"]
        return self._start(proc_name, [*args, *(extra or [])], stdin=True)

    def start_recorder(self, name: str, output: Path | None = None) -> Proc:
        config = self.workdir / f"{name}.toml"
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
        for name in reversed(list(self.procs)):  # operators first, the router last
            self.stop(name)
            stdin = self.procs[name].stdin
            if stdin is not None and not stdin.closed:
                with contextlib.suppress(BrokenPipeError):
                    stdin.close()

    def __enter__(self) -> Fleet:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
