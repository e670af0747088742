"""STOP always reachable, replays never believed: seen from outside a real robot node process.

One deployment for the module: the robot node as its own process (as
deployed) on the UR simulator, with a roster of real signing keys; the
operators are a raw signed client written from docs/protocol.md and, for the
page, a real operator node behind the dashboard server's WebSocket. The arm
is read from the UR simulator, what the robot believes from its heartbeat's
stats and its log.
"""

from __future__ import annotations

import json
import signal
import threading
import time
from pathlib import Path

import pytest
import zmq
from tests_support import ProtocolOperator, on_the_wire, readable
from websockets.sync.client import connect

from common.clocks.clock import now_ns
from common.wire.codec import SIG_ENTRY_BYTES, SIG_TAG, encode
from common.wire.messages import Command, Heartbeat, VideoSignal
from common.wire.signing import generate_key_files, load_signer
from common.wire.transport import Publisher, Subscriber
from harness.bench.command_path import RobotUnderCommands
from robot_side.arm.sim.commands import COMMAND_NAMES

pytestmark = [
    pytest.mark.slow,
    pytest.mark.timeout(240),
    # the page's operator node and dashboard run as threads of this process: at the operator
    # unit's niceness, as deployed (a test process at the lanes' -5 beside busy loops took a
    # page's STOP 24 ms past the budget)
    pytest.mark.usefixtures("quiet_gc", "robot_node_priority_module"),
]

JOG = (0.03, 0.0, 0.0, 0.0, 0.0, 0.0)
STOP_BUDGET_NS = 400_000_000  # the product's stop budget


class Cell:
    """The robot process, its roster's keys, and a signed raw operator holding the lease."""

    def __init__(self, workdir: Path) -> None:
        self.workdir = workdir
        keys = workdir / "keys"
        keys.mkdir()
        entries, self.secrets = [], {}
        for name, role in (("ctl", "controller"), ("page", "observer")):
            public, self.secrets[name] = generate_key_files(keys, name)
            entries.append(
                f'[[operator]]\nname = "{name}"\nrole = "{role}"\n'
                f'signing_key = "{public.read_text().strip()}"\n'
            )
        self.roster = workdir / "roster.toml"
        self.roster.write_text("\n".join(entries))
        self.signer = load_signer(self.secrets["ctl"])
        self.ctx = zmq.Context()
        self.rig = RobotUnderCommands(workdir)
        self.op: ProtocolOperator | None = None
        self._jogs = 0  # each test's jog goes the other way: the arm stays inside its box

    def __enter__(self) -> Cell:
        rig = self.rig.__enter__()
        with rig.config.open("a") as f:  # [robot.link] is the file's last table
            f.write(f'roster_file = "{self.roster}"\n')
        self.restart_robot()
        self.op = self.new_operator(session=11)
        self.op.sync()
        self.hold_lease()
        return self

    def __exit__(self, *exc: object) -> None:
        self.rig.__exit__(*exc)
        self.ctx.destroy(linger=0)

    def new_operator(self, session: int) -> ProtocolOperator:
        rig = self.rig
        pub = Publisher(self.ctx, rig.command_endpoint, bind=False, signer=self.signer)
        return ProtocolOperator(
            Subscriber(self.ctx, rig.telemetry_endpoint, bind=False), pub, session=session
        )

    def restart_robot(self) -> None:
        proc = self.rig.proc
        proc.send_signal(signal.SIGTERM)
        proc.wait(20)
        self.rig.start_node()

    def stats(self) -> dict[str, float]:
        return self.rig.telemetry.robot_stats()

    def robot_heartbeat(self) -> Heartbeat | None:
        beats = [m for _, m in self.op.received if isinstance(m, Heartbeat)]
        return beats[-1] if beats else None

    def hold_lease(self, timeout_s: float = 15.0) -> None:
        deadline = time.monotonic() + timeout_s
        while True:
            hb = self.robot_heartbeat()
            if hb is not None and hb.lease_holder == self.signer.public:
                return
            assert time.monotonic() < deadline, "the controller never got the lease"
            self.op.command("lease_request")
            self.op.pump(0.25)

    def resume(self) -> None:
        for _ in range(10):  # a resume must be fresh: one that waited on a starved test is not
            if not self.stats().get("arm_stop_latched"):
                return
            self.hold_lease()
            self.op.command("arm_resume")
            self.until(lambda: not self.stats().get("arm_stop_latched"), 0.5)
        raise AssertionError(f"the holder's resume never released the stop:\n{self.log()}")

    def until(self, cond, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while not cond():
            if time.monotonic() > deadline:
                return False
            self.op.pump(0.02)
        return True

    def jog_until_moving(self, timeout_s: float = 10.0) -> None:
        self._jogs += 1
        deadline = time.monotonic() + timeout_s
        t0 = now_ns()
        while not self.rig.arm.moving_between(t0, now_ns(), above=0.01):
            assert time.monotonic() < deadline, f"the jog never moved the arm:\n{self.log()}"
            hb = self.robot_heartbeat()
            if hb is None or hb.lease_holder != self.signer.public:
                self.hold_lease()  # a starved test process fell silent past the deadman
            self.op.command("arm_jog", velocity=self.jog)
            self.op.pump(0.05)

    @property
    def jog(self) -> tuple[float, ...]:
        return JOG if self._jogs % 2 else tuple(-v for v in JOG)

    def keep_jogging(self, seconds: float) -> None:
        """A key still held after the stop: the latch must keep the arm still."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.op.command("arm_jog", velocity=self.jog)
            self.op.pump(0.05)

    def still_after(self, t_stop: int) -> list[int]:
        return self.rig.arm.moving_between(t_stop + STOP_BUDGET_NS, now_ns(), above=1e-3)

    def log(self) -> str:
        return self.rig.log.read_text()

    def controller_after(self, t_ns: int) -> str:
        """What the UR simulator read, acted on and answered from half a second before
        ``t_ns`` on (ms from it; the speedL to rest, the speedStop and its "done"): whether
        a late stop reached the controller late or was acted on late."""
        events = self.rig.arm_sim.command_events(t_ns / 1e9 - 0.5)
        return "\n".join(
            f"{(t - t_ns / 1e9) * 1e3:+.0f} ms: {COMMAND_NAMES.get(cmd, cmd)} {what}"
            for t, cmd, what in events
        )

    def log_after(self, t_ns: int) -> str:
        """The robot's log from about a second before ``t_ns`` (its lines carry wall-clock
        time; this clock is monotonic): where a late stop waited, the node or its arm
        process (a silence on the controller's wire is logged there)."""
        since = time.time() - (now_ns() - t_ns) / 1e9 - 1.0
        since_text = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(since))
        lines = [line for line in self.log().splitlines() if line[:19] >= since_text]
        return "\n".join(lines[-40:])


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    with Cell(tmp_path_factory.mktemp("stopreplay")) as c:
        yield c


def _signed(signer, body: dict) -> bytes:
    """``body`` signed as ``common.wire.codec.encode`` signs (its sig last, over all before it)."""
    packed = on_the_wire(b"CMND", dict(body, sig=bytes(64)))
    signed = packed[:-SIG_ENTRY_BYTES]
    return signed + SIG_TAG + signer.sign(signed)


BAD_STAMPS = {"nan": float("nan"), "string": "soon", "missing": None, "u64": 2**64 - 1}


@pytest.mark.parametrize("stamp", sorted(BAD_STAMPS))
def test_a_stop_with_a_malformed_stamp_on_the_wire_stops_and_latches_the_arm(cell, stamp):
    cell.resume()
    cell.jog_until_moving()
    op = cell.op
    op.seq += 1
    body = readable(
        encode(
            Command(seq=op.seq, t_send_ns=now_ns(), action="arm_stop", session=op.session,
                    echo_session=op.robot_session),
            signer=cell.signer,
        )
    )  # fmt: skip
    body.pop("sig")
    if BAD_STAMPS[stamp] is None:
        body.pop("t_send_ns")
    else:
        body["t_send_ns"] = BAD_STAMPS[stamp]
    before = cell.stats().get("arm_stops_malformed", 0.0)
    t_stop = now_ns()
    op.pub.sock.send(_signed(cell.signer, body))
    cell.keep_jogging(0.8)
    moving = cell.still_after(t_stop)
    assert not moving, (
        f"the arm moved {(moving[-1] - t_stop) / 1e6:.0f} ms after the stop; the robot's log:\n"
        f"{cell.log_after(t_stop)}\nthe controller's commands:\n{cell.controller_after(t_stop)}"
    )
    stats = cell.stats()
    assert stats.get("arm_stop_latched") == 1.0, stats
    assert stats.get("arm_stops_malformed", 0.0) == before + 1
    assert "arm_stop with malformed fields, acted on" in cell.log()


@pytest.fixture(scope="module")
def page(cell):
    """A real signed operator node (an observer's key) and the dashboard serving its page."""
    from operator_side.dashboard import Dashboard, DashboardConfig
    from operator_side.node import OperatorNode
    from operator_side.node.config import OperatorConfig
    from operator_side.servos.in_memory import InMemoryServoBus

    oc = OperatorConfig()
    oc.link.telemetry_endpoint = cell.rig.telemetry_endpoint
    oc.link.command_endpoint = cell.rig.command_endpoint
    oc.link.signing_key_file = cell.secrets["page"]
    node = OperatorNode(oc, InMemoryServoBus())
    stop = threading.Event()
    thread = threading.Thread(target=node.run, args=(stop,), daemon=True)
    thread.start()
    dashboard = Dashboard(node, DashboardConfig(port=0))
    dashboard.start()
    try:
        assert cell.until(lambda: node.counters["heartbeats_received"] > 2, 15)
        yield dashboard
    finally:
        dashboard.stop()
        stop.set()
        thread.join(10)


PAGE_STAMPS = {"400 digits": "1" * 400, "NaN": "NaN", "string": '"soon"', "missing": None}


@pytest.mark.parametrize("stamp", sorted(PAGE_STAMPS))
def test_a_stop_with_a_malformed_page_stamp_stops_and_latches_the_arm(cell, page, stamp):
    cell.resume()
    cell.jog_until_moving()
    raw = PAGE_STAMPS[stamp]
    text = '{"type": "command", "action": "arm_stop"'
    text += "}" if raw is None else f', "t_page_ms": {raw}}}'
    with connect(page.ws_url) as ws:
        t_stop = now_ns()
        ws.send(text)
        while True:
            reply = json.loads(ws.recv(timeout=5))
            if reply.get("type") == "ack":
                break
    assert reply["ok"], reply
    cell.keep_jogging(0.8)
    moving = cell.still_after(t_stop)
    assert not moving, (
        f"the arm moved {(moving[-1] - t_stop) / 1e6:.0f} ms after the page's stop; the robot's "
        f"log:\n{cell.log_after(t_stop)}\nthe controller's commands:\n"
        f"{cell.controller_after(t_stop)}"
    )
    assert cell.stats().get("arm_stop_latched") == 1.0


def test_a_replayed_heartbeat_and_video_signal_are_refused(cell):
    """A second boot of the controller's key: each message accepted once, its copy refused."""
    op = cell.op
    run = op.robot_session
    pub = op.pub
    beat = pub.send(
        Heartbeat(seq=1, t_send_ns=now_ns(), node="operator", state="ok", session=99,
                  echo_session=run)
    )  # fmt: skip
    bye = pub.send(
        VideoSignal(seq=1, t_send_ns=now_ns(), kind="bye", viewer=12345, session=99,
                    echo_session=run)
    )  # fmt: skip
    op.pump(0.3)
    before = cell.stats()
    pub.sock.send(beat)
    pub.sock.send(bye)
    replays = ("heartbeats_replayed", "video_signals_replayed")
    assert cell.until(lambda: "video_signals_replayed" in cell.stats(), 5), (
        {k: v for k, v in cell.stats().items() if k in replays or k.startswith("messages_")},
        [line for line in cell.log().splitlines() if "refused" in line or "replay" in line][-8:],
    )
    after = cell.stats()
    assert after["heartbeats_replayed"] == before.get("heartbeats_replayed", 0.0) + 1
    assert after["video_signals_replayed"] == before.get("video_signals_replayed", 0.0) + 1
    # logged once per burst (the second refusal falls in the first one's burst)
    assert "replay window): heartbeats_replayed: Heartbeat from ctl" in cell.log()


def test_a_stop_replayed_after_a_robot_restart_is_refused_and_a_fresh_one_latches(cell):
    op = cell.op
    cell.resume()
    op.seq += 1
    captured = op.pub.send(
        Command(seq=op.seq, t_send_ns=now_ns(), action="arm_stop", session=op.session,
                echo_session=op.robot_session)
    )  # fmt: skip
    assert cell.until(lambda: cell.stats().get("arm_stop_latched") == 1.0, 5)
    # a stop of an earlier boot of the same key, which the robot never saw
    dead_boot = op.pub.send(
        Command(seq=5, t_send_ns=now_ns(), action="arm_stop", session=12345,
                echo_session=op.robot_session)
    )  # fmt: skip
    cell.restart_robot()
    op.pub.sock.send(captured)  # the recording, replayed into the new run
    op.pub.sock.send(dead_boot)
    assert cell.until(lambda: "arm_stops_unproven" in cell.stats(), 10), cell.stats()
    stats = cell.stats()
    assert stats.get("arm_stops_before_this_run") == 1.0, stats
    assert not stats.get("arm_stop_latched"), stats
    log = cell.log()
    assert "sent before this robot run started (a replay): refused" in log
    assert "never proved it hears this run within 2 s" in log
    # nothing latched: the holder's jog moves the arm (read from the simulator)
    cell.hold_lease()
    cell.jog_until_moving()
    # a genuine STOP the moment the robot is back latches at once
    cell.restart_robot()
    t_stop = now_ns()
    op.command("arm_stop")
    assert cell.until(lambda: cell.stats().get("arm_stop_latched") == 1.0, 5), cell.stats()
    print(f"\nfresh stop after a restart latched in {(now_ns() - t_stop) / 1e6:.0f} ms")
