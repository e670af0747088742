"""A router, robots and operators as real processes on this machine (tests, bench).

The fabric across sites: a Zenoh router made from the roster (``deepxpalm
router``), every hop QUIC with the members' certificates; every operator
signs, every robot signs its stream, and one roster says who is who:
the same layout as three machines (docs/deploy.md), on 127.0.0.1. ``Fleet``
writes the keys, the roster and each process's config into one work folder,
starts the processes as the catalogue's units (``deploy.units``) and stops
them all. The router and the video server bind free ports and say which in
their ``READY=1``: ``start_router`` and ``start_video`` return once they
did, and the processes started after them are pointed there.
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

from common.keys.roster import operator_entry, robot_entry
from common.web import web_token
from common.wire.signing import generate_key_files, load_public_key, write_secret_file
from deploy.keys_cli import generate
from deploy.units.readiness import Ready
from deploy.units.service import Service

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
listen_endpoint = "{listen}"
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
    """One process of the fleet: its unit's service, its statistics file and its stdin."""

    name: str
    service: Service
    stats_path: Path
    takes_stdin: bool = False

    @property
    def popen(self) -> subprocess.Popen:
        assert self.service.popen is not None, f"{self.name} was never started"
        return self.service.popen

    @property
    def log_path(self) -> Path:
        return self.service.log

    @property
    def stdin(self) -> IO[str] | None:
        popen = self.service.popen
        return popen.stdin if self.takes_stdin and popen is not None else None

    def start(self) -> Proc:
        self.service.start()
        return self

    def wait_ready(self, timeout_s: float = 60.0) -> Ready:
        """What it said with READY=1 (its endpoints), once it did; ``NotReady`` otherwise."""
        return self.service.wait_ready(timeout_s)

    def send(self, command: dict[str, Any]) -> None:
        """One JSON command line to an operator started with ``--commands-from-stdin``."""
        self.stdin.write(json.dumps(command) + "\n")
        self.stdin.flush()

    def stats(self) -> dict[str, float]:
        return json.loads(self.stats_path.read_text()) if self.stats_path.exists() else {}

    def log_text(self) -> str:
        return self.service.log_text()


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
        #: where the router listens: said by its READY=1 (``start_router``), or by whoever
        #: runs one (a router in the test's own process)
        self.router_endpoint = ""

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
    def process(
        self,
        name: str,
        unit: str,
        args: list[str],
        stdin: bool = False,
        *,
        stats: bool = True,
        watchdog: bool = False,
    ) -> Proc:
        """``deepxpalm ARGS`` as catalogue ``unit`` (its niceness), not started yet: its log
        and (``stats``) statistics in the workdir (a new one's log replaces an old one's).
        ``watchdog``: under its unit's WatchdogSec= (for whoever checks it: the fault
        matrix's supervisor)."""
        log_path = self.workdir / f"{name}.log"
        log_path.unlink(missing_ok=True)
        stats_path = self.workdir / f"{name}-stats.json"
        service = Service(
            unit,
            [*args, *(["--stats-file", str(stats_path)] if stats else [])],
            log_path,
            name=name,
            env=self.env,
            stdin=subprocess.PIPE if stdin else subprocess.DEVNULL,
            watchdog=watchdog,
            text=True,
        )
        proc = Proc(name, service, stats_path, stdin)
        old = self.procs.get(name)
        if old is not None:  # the same name started again: its socket is the new one's
            old.service.close()
        self.procs[name] = proc
        return proc

    def router(self, name: str = "router") -> Proc:
        """The fabric's Zenoh router, its access control made from the (router's) roster, on
        the port it had (a restart) or a free one; not started."""
        config = self._router_config(name)
        return self.process(name, "router", ["-v", "router", "--config", str(config)])

    def _router_config(self, name: str) -> Path:
        config = self.workdir / f"{name}.toml"
        write_secret_file(
            config,
            _ROUTER_TOML.format(
                listen=self.router_endpoint or "quic/127.0.0.1:0",
                roster=self.router_roster,
                cert_dir=self.cert_dir,
                status=self.workdir / f"{name}-status.json",
            ),
        )
        return config

    def start_router(self, name: str = "router", timeout_s: float = 30.0) -> Proc:
        """The router, once it said READY=1: robots and operators started after it go there."""
        proc = self.router(name).start()
        self.router_ready(proc.wait_ready(timeout_s), name)
        return proc

    def router_ready(self, ready: Ready, name: str = "router") -> None:
        """Where the router listens (its READY=1): the members go there, and a restarted
        router binds it again (its config says it from now on)."""
        self.router_endpoint = ready.endpoints["listen"]
        self._router_config(name)

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

    def start_robot(self, name: str, arm_host: str | None, *args: Any, **options: Any) -> Proc:
        """:meth:`robot` ``name``, started (the arguments as there)."""
        return self.robot(name, arm_host, *args, **options).start()

    def robot(
        self,
        name: str,
        arm_host: str | None,
        rate_hz: float = 60.0,
        video_url: str = "",
        devices: str = SCRIPTED_TACTILE,
    ) -> Proc:
        """Robot ``name`` (:meth:`robot_config`), not started."""
        config = self.robot_config(name, arm_host, rate_hz, video_url, devices)
        return self.process(name, "robot", ["-v", "robot", "--config", str(config)])

    def start_video(
        self,
        name: str = "video",
        fps: float = 15.0,
        port: int = 0,
        settings: tuple[str, ...] = (),
        timeout_s: float = 60.0,
    ) -> tuple[Proc, str]:
        """A video server (the stamped test pattern, 320x240) on loopback, once it said where
        it serves; (process, its URL, token included: a robot's link.video_url)."""
        proc = self.video(name, fps, port, settings).start()
        return proc, self.video_url(name, proc.wait_ready(timeout_s))

    def video(
        self, name: str = "video", fps: float = 15.0, port: int = 0, settings: tuple[str, ...] = ()
    ) -> Proc:
        """A video server, not started: on ``port`` (the one it had before a restart; 0: a
        free one, said in its READY=1). Its token file stays in the workdir, so a restarted
        server keeps its token. ``settings``: more ``--set`` overrides (``ice_timeout_s=3``)."""
        settings = (*settings, f"port={port}", "test_pattern.width=320", "test_pattern.height=240")
        settings += (f"test_pattern.fps={fps}", f'token_file="{self.workdir / name}.token"')
        args = ["-v", "video", *(a for s in settings for a in ("--set", s))]
        return self.process(name, "video", args)

    def video_url(self, name: str, ready: Ready) -> str:
        """Video server ``name``'s URL (its READY=1's), with the token of its file."""
        token = web_token.token_file(self.workdir / f"{name}.token", "video token_file")
        return web_token.with_token(ready.endpoints["signalling"], token)

    def start_operator(self, name: str, robot: str, **options: Any) -> Proc:
        """:meth:`operator` ``name`` following ``robot``, started (``options`` as there)."""
        return self.operator(name, robot, **options).start()

    def operator(
        self,
        name: str,
        robot: str,
        *,
        request_control: bool = False,
        want_frames: bool = True,
        extra: list[str] | None = None,
        servos: str = 'kind = "in_memory"',
        router_endpoint: str | None = None,
        watchdog: bool = False,
    ) -> Proc:
        """An operator process, not started; its config written. ``servos`` is its
        ``[operator.servos]`` TOML body, ``router_endpoint`` another path to the router (a
        link simulator's datagram port)."""
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
        argv = [*args, *(extra or [])]
        return self.process(proc_name, "operator", argv, stdin=True, watchdog=watchdog)

    def start_recorder(self, name: str, output: Path | None = None) -> Proc:
        return self.recorder(name, output).start()

    def recorder(self, name: str, output: Path | None = None) -> Proc:
        """A recorder of every robot of the fleet, not started."""
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
        return self.process(name, "recorder", ["-v", "record", "--config", str(config)])

    def wait_for(
        self,
        cond: Callable[[], bool],
        timeout_s: float,
        what: str,
        detail: Callable[[], object] | None = None,
    ) -> None:
        """Poll ``cond`` until true; else fail naming ``what`` (and what ``detail`` shows then),
        with every process's log tail."""
        deadline = time.monotonic() + timeout_s
        while not cond():
            if time.monotonic() > deadline:
                logs = "\n".join(f"--- {n}\n{p.log_text()[-3000:]}" for n, p in self.procs.items())
                seen = f" ({detail()})" if detail is not None else ""
                raise AssertionError(f"timed out waiting for {what}{seen}\n{logs}")
            time.sleep(0.05)

    def stop(self, name: str, sig: int | None = None, timeout_s: float = 15.0) -> int:
        """``sig`` (default: what ``systemctl stop`` sends), then a kill; the exit code."""
        service = self.procs[name].service
        if sig is None:
            service.stop(timeout_s)
        else:
            service.stop(timeout_s, sig)
        return service.popen.returncode

    def close(self) -> None:
        for name in reversed(list(self.procs)):  # operators first, the router last
            proc = self.procs[name]
            if proc.service.popen is not None:
                self.stop(name)
            stdin = proc.stdin
            if stdin is not None and not stdin.closed:
                with contextlib.suppress(BrokenPipeError):
                    stdin.close()
            proc.service.close()

    def __enter__(self) -> Fleet:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
