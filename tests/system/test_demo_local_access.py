"""``deepxpalm demo`` as a user runs it, attacked by another process of the same machine.

The demo's default links (the robot's command port and the link simulator's
operator-side ports, found in the configs its children run with) are plain
loopback TCP to anyone unless they are CURVE. A client that knows only the
ports, as ``docs/protocol.md`` describes the protocol, tries what a plain link
let it do: echo heartbeats, jog the arm at 50 mm/s, resume
a stop, open the gripper, offer to watch the camera. The arm is read from
the UR simulator's own RTDE interface; the client's sockets say what it got.

The same run checks where the dashboard's token may appear: once on stderr at
start, never in the live view's frames, the logs, or the recording's metadata;
and the run's secret key files are 0600 in a 0700 directory.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import stat
import time
import tomllib
from pathlib import Path

import numpy as np
import pytest
import zmq
from tests_support import child_processes

from common.clocks.clock import now_ns
from common.wire.messages import Command, Heartbeat, VideoSignal
from common.wire.transport import Publisher, Subscriber
from deploy.units.readiness import NotReady
from deploy.units.service import Service

pytestmark = [pytest.mark.slow, pytest.mark.timeout(240)]

TOKEN = "fixed-demo-page-token-for-the-redaction-check"
DURATION_S = 40.0
JOG = (0.05, 0.0, 0.0, 0.0, 0.0, 0.0)  # 50 mm/s along x, as the attack in the report


def _free_loopback_host() -> str:
    """A 127.0.0.x whose UR ports are free, so the test can read the simulated arm."""
    for last in range(200, 250):
        host = f"127.0.0.{last}"
        with socket.socket() as s:
            try:
                s.bind((host, 30004))  # RTDE
            except OSError:
                continue
        return host
    raise RuntimeError("no free 127.0.0.x for the UR simulator")


class Demo:
    """The demo with its live view (stdout to a file), dashboard, recording and the arm."""

    def __init__(self, tmp: Path, *extra: str) -> None:
        self.tmp = tmp
        self.record = tmp / "rec"
        self.arm_host = _free_loopback_host()
        self.stdout, self.stderr = tmp / "stdout", tmp / "stderr"
        argv = ["demo", "--dashboard", *extra]
        argv += ["--duration", str(DURATION_S), "--record", str(self.record), "--no-video"]
        argv += ["--set", "operator.dashboard.port=0"]  # a free one, said when ready
        argv += ["--set", f'operator.dashboard.token="{TOKEN}"']
        argv += ["--set", f'robot.arm={{kind="simulated", sim={{host="{self.arm_host}"}}}}']
        self.service = Service("demo", argv, self.stderr, stdout=self.stdout)
        self.proc = self.service.start()
        self.result: tuple[int, str, str] | None = None

    def wait_for_dashboard(self, timeout_s: float = 120.0) -> None:
        """Until the demo said READY=1: every process of it up, its page served."""
        try:
            self.service.wait_ready(timeout_s)
        except NotReady as e:
            raise RuntimeError(f"the demo never came up: {e}: {self.err()[-3000:]}") from None

    def err(self) -> str:
        return self.stderr.read_text(errors="replace")

    def endpoints(self) -> dict[str, str]:
        """The robot's and the link simulator's endpoints: each bound a port of its own and
        said it; the demo wrote them into the robot's and the operator's configs, found in
        their command lines as ``ps`` shows them."""
        children = child_processes(self.proc.pid)

        def link(role: str) -> dict[str, str]:
            with open(f"/proc/{children[role]}/cmdline", "rb") as f:
                words = f.read().decode().split("\0")
            config = tomllib.loads(Path(words[words.index("--config") + 1]).read_text())
            return config[role]["link"]

        robot, operator = link("robot"), link("operator")
        return {
            "robot-telemetry": robot["telemetry_endpoint"],
            "robot-commands": robot["command_endpoint"],
            "operator-telemetry": operator["telemetry_endpoint"],
            "operator-commands": operator["command_endpoint"],
        }

    def finish(self) -> tuple[int, str, str]:
        if self.result is None:
            if self.proc.poll() is None:
                self.proc.send_signal(signal.SIGINT)
            self.proc.wait(timeout=90)
            out = self.stdout.read_text(errors="replace")
            self.result = (self.proc.returncode, out, self.err())
        return self.result


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    d = Demo(tmp_path_factory.mktemp("demo-local"))
    try:
        d.wait_for_dashboard()
        yield d
    finally:
        d.service.stop(0)
        d.service.close()


class ArmReader:
    """ur-rtde's receive interface on the simulated controller: where the tool is."""

    def __init__(self, host: str) -> None:
        import rtde_receive

        self.rtde = rtde_receive.RTDEReceiveInterface(host, 125.0, ["actual_TCP_pose"])

    def position(self) -> np.ndarray:
        return np.array(self.rtde.getActualTCPPose()[:3])


def _attack(telemetry: str, commands: str, seconds: float) -> dict[str, int]:
    """The protocol's operator on plain sockets: heartbeats echoing the robot's, a jog
    at 50 mm/s at 20 Hz, a resume, a gripper open and a video offer; what came back."""
    ctx = zmq.Context()
    sub = Subscriber(ctx, telemetry, bind=False, name="local client")
    pub = Publisher(ctx, commands, bind=False)
    got: dict[str, int] = {}
    echo: tuple[int | None, int | None] = (None, None)
    seq = cmd_seq = 0
    end = time.monotonic() + seconds
    try:
        while time.monotonic() < end:
            for msg, t_recv in sub.drain():
                got[type(msg).__name__] = got.get(type(msg).__name__, 0) + 1
                if isinstance(msg, Heartbeat):
                    echo = (msg.t_send_ns, t_recv)
            seq += 1
            t = now_ns()
            pub.send(
                Heartbeat(
                    seq=seq,
                    t_send_ns=t,
                    node="operator",
                    state="ok",
                    echo_t_send_ns=echo[0],
                    echo_t_recv_ns=echo[1],
                )
            )
            for action, fields in (
                ("arm_resume", {}),
                ("gripper_open", {}),
                ("arm_jog", {"velocity": JOG}),
            ):
                cmd_seq += 1
                cmd = Command(seq=cmd_seq, t_send_ns=now_ns(), action=action, session=99, **fields)
                pub.send(cmd)
            if seq % 20 == 1:
                pub.send(
                    VideoSignal(seq=seq, t_send_ns=t, kind="offer", viewer=4242, sdp="v=0\r\n")
                )
            sub.poll(0.05)
    finally:
        sub.close()
        pub.close()
        ctx.term()
    return got


def test_a_local_process_without_the_key_moves_nothing_and_hears_nothing(demo):
    ends = demo.endpoints()
    arm = ArmReader(demo.arm_host)
    before = arm.position()
    paths = {
        "robot": (ends["robot-telemetry"], ends["robot-commands"]),
        "link simulator": (ends["operator-telemetry"], ends["operator-commands"]),
    }
    for where, (tel, cmd) in paths.items():
        got = _attack(tel, cmd, 2.0)
        moved_mm = 1e3 * float(np.linalg.norm(arm.position() - before))
        # a plain link let the same client jog 85-91 mm in 1.5 s
        assert moved_mm < 1.0, f"through the {where}: the arm moved {moved_mm:.1f} mm"
        # not a heartbeat, not a stimulus, not a video answer: no handshake, nothing
        assert got == {}, f"through the {where} the client received {got}"
    # the operator's own node, holding the key, was served all along
    code, out, err = demo.finish()
    assert code == 0, err[-3000:]
    summary = json.loads(out[out.rindex("\n{") :])
    assert summary["security"] == "curve" and summary["errors"] == []
    # the robot kept publishing, and the operator's node got every stimulus from its first
    # on: no gap in their sequence (the link is TCP; what the robot published before the
    # operator's node was up, which a busy machine makes longer, is no gap); a count of its
    # own would judge the machine's speed, not the attack
    published, received = summary["stimuli_published"], summary["stimuli_received"]
    link = summary["link"]
    assert published >= 20 and received >= 20, (published, received)
    assert link["lost"] == 0 and link["telemetry_reopened"] == 0, link


def test_the_token_is_shown_once_and_the_keys_are_0600(demo):
    _, out, err = demo.finish()
    summary = json.loads(out[out.rindex("\n{") :])
    # printed once, on stderr at start (the line scripts read), and nowhere after it
    assert err.count(TOKEN) == 1 and "dashboard http" in err
    frames = out[: out.rindex("\n{")]
    assert frames.count("\x1b[2J") > 50  # the live view drew
    assert "dashboard http://127.0.0.1:" in frames and TOKEN not in frames
    workdir = Path(summary["logs"])
    assert stat.S_IMODE(workdir.stat().st_mode) == 0o700
    for log in workdir.glob("*.log"):
        assert TOKEN not in log.read_text(errors="replace"), log
    url_file = workdir / "dashboard.url"  # where the live view points for the full address
    assert TOKEN in url_file.read_text() and stat.S_IMODE(url_file.stat().st_mode) == 0o600
    # the operator node's status file holds the address too (the demo reads it from there)
    status = workdir / "operator-status.json"
    assert TOKEN in status.read_text() and stat.S_IMODE(status.stat().st_mode) == 0o600
    keys = workdir / "keys"
    assert stat.S_IMODE(keys.stat().st_mode) == 0o700
    secrets = list(keys.rglob("*.key_secret"))
    assert len(secrets) == 2
    for path in secrets:
        assert stat.S_IMODE(path.stat().st_mode) == 0o600, path
    # the recording's metadata: the config without its secret
    from mcap.reader import make_reader

    with open(demo.record / "operator.mcap", "rb") as f:
        metadata = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    config = metadata["deepxpalm.node"]["config_toml"]
    assert "[operator.dashboard]" in config and "token = (set; not shown)" in config
    assert TOKEN not in json.dumps(metadata)
    # the session record `deepxpalm export` reads, written by the operator node's process
    assert metadata["deepxpalm.session"] == {"scene": "demo", "network_scenario": "lan"}
    assert os.path.exists(demo.record / "robot.mcap")
