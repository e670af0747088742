"""Running nodes for the fuzz tests: each in a thread, on random loopback ports.

A rig plays the node's peer over real ZeroMQ: a "good" socket keeps a
valid stream going (what the node must keep serving) and an "evil" socket
carries the fuzz. Sends are paced on the node's own receive counter, so no
message is dropped at a high-water mark and every rejection can be
accounted for exactly. The devices behind the robot node are the project's
real safety layers (``Arm``, ``Gripper``) over its memory kinds, which keep
what they were told.
"""

from __future__ import annotations

import math
import multiprocessing
import os
import threading
import time
from typing import Any

import msgpack
import numpy as np
import zmq
from fuzz_mutate import produce

from common.clocks.clock import now_ns
from common.wire.codec import decode, encode
from common.wire.messages import Command, Heartbeat, Stimulus
from common.wire.transport import last_endpoint
from operator_side.node import OperatorNode
from operator_side.node.config import OperatorConfig
from operator_side.servos.in_memory import InMemoryServoBus, InMemoryServoBusConfig
from robot_side.arm.memory import MemoryArm
from robot_side.gripper.memory import MemoryGripper
from robot_side.node import RobotNode
from robot_side.node.config import RobotConfig
from robot_side.tactile.script import GraspScript, GraspStep
from robot_side.tactile.scripted import ScriptedTactileConfig, ScriptedTactileSensor

BIG_HWM = 1_000_000

#: Malformed messages each node gets per run: the first 25,000 of the 100,000 the suite sent
#: before (same seeds), which took about 12 s of a deployment lane's two cores per node.
#: ``DEEPXPALM_FUZZ_N`` sends more and ``DEEPXPALM_FUZZ_SEED`` draws other mutants
#: (docs/testing.md). Not a fresh seed each run: the module's later tests share the node
#: with these mutants, and a seed the suite has not run can leave it in a state they do not
#: expect (one made the hypothesis test's syncs time out in a full lane; not yet traced: 224
#: other seeds, the module alone and beside two busy loops, all passed).
N_MALFORMED = int(os.environ.get("DEEPXPALM_FUZZ_N", "25000"))


def fuzz_seed(default: int) -> int:
    """This run's seed: ``DEEPXPALM_FUZZ_SEED`` if set, else ``default``; printed either way."""
    seed = int(os.environ.get("DEEPXPALM_FUZZ_SEED") or default)
    print(f"fuzz seed {seed} (replay: DEEPXPALM_FUZZ_SEED={seed} DEEPXPALM_FUZZ_N={N_MALFORMED})")
    return seed


def _pub(ctx: zmq.Context, endpoint: str, *, bind: bool) -> zmq.Socket:
    s = ctx.socket(zmq.PUB)
    s.setsockopt(zmq.LINGER, 0)
    s.setsockopt(zmq.SNDHWM, BIG_HWM)
    if bind:
        s.bind(endpoint)
    else:
        s.connect(endpoint)
    return s


def _sub(ctx: zmq.Context, endpoint: str, *, bind: bool) -> zmq.Socket:
    s = ctx.socket(zmq.SUB)
    s.setsockopt(zmq.LINGER, 0)
    s.setsockopt(zmq.SUBSCRIBE, b"")
    if bind:
        s.bind(endpoint)
    else:
        s.connect(endpoint)
    return s


def wait_for(cond, timeout_s: float, step_s: float = 0.002) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(step_s)
    return bool(cond())


def handled_all(rig: Any, timeout_s: float) -> bool:
    """True once the rig's node has read everything sent and finished the loop turn that did.

    The socket's receive counter moves as each message is read, before it is
    decoded, counted as rejected, or acted on, all later in the same loop
    turn; a counter read right after the last receive could miss them. The
    next turn's wake-up proves that turn is over.
    """
    deadline = time.monotonic() + timeout_s
    if not wait_for(lambda: rig.received() >= rig.sent or not rig.alive(), timeout_s):
        return False
    turn = rig.node.counters["wakeups"]
    left = max(0.0, deadline - time.monotonic())
    return wait_for(lambda: rig.node.counters["wakeups"] > turn or not rig.alive(), left)


# ------------------------------------------------------------ device checks
def arm_violations(arm: MemoryArm) -> list[str]:
    """Every jog the driver was told must be finite and inside the speed caps; no moves."""
    lim = arm.limits
    bad = [f"a move to {pose.tolist()} (nothing on the wire asks for one)" for pose, _ in arm.moves]
    for v in arm.sent_jogs:
        if v.shape != (6,) or not np.isfinite(v).all():
            bad.append(f"non-finite or misshapen jog {v!r}")
        elif np.linalg.norm(v[:3]) > lim.max_linear_speed_m_s * (1 + 1e-9):
            bad.append(f"jog over the linear cap: {v.tolist()}")
        elif np.linalg.norm(v[3:]) > lim.max_angular_speed_rad_s * (1 + 1e-9):
            bad.append(f"jog over the angular cap: {v.tolist()}")
    return bad


def gripper_violations(gripper: MemoryGripper) -> list[str]:
    """Every register value the gripper was sent must be a byte."""
    bad = []
    for cmd in gripper.commands:
        for v in cmd[:3]:
            if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= 255:
                bad.append(f"gripper register value {v!r} in {cmd}")
    return bad


# ---------------------------------------------------------------- operator
def stimulus_for(pattern: int, value: float = 4.0) -> np.ndarray:
    from common.tactile.contract import MASKS_F32

    return (MASKS_F32[pattern] * np.float32(value)).astype(np.float32)


class OperatorRig:
    """An operator node whose "robot" is this test: good stimuli and heartbeats, plus fuzz."""

    def __init__(self) -> None:
        self.ctx = zmq.Context()
        self.pub = _pub(self.ctx, "tcp://127.0.0.1:*", bind=True)  # the robot's telemetry PUB
        self.cmd_sub = _sub(self.ctx, "tcp://127.0.0.1:*", bind=True)  # the robot's command SUB
        oc = OperatorConfig()
        oc.link.telemetry_endpoint = last_endpoint(self.pub)
        oc.link.command_endpoint = last_endpoint(self.cmd_sub)
        self.bus = InMemoryServoBus(InMemoryServoBusConfig(max_records=1_000_000))
        self.node = OperatorNode(oc, self.bus)
        self.stop = threading.Event()
        self.error: list[BaseException] = []
        self.thread = threading.Thread(target=self._run, name="fuzz-operator", daemon=True)
        self.sent = 0
        self.stim_seq = 0
        self.hb_seq = 0
        self.current: Stimulus | None = None
        self._send_lock = threading.Lock()
        self._beating = threading.Event()
        self._beat_thread = threading.Thread(target=self._beat, name="fuzz-robot-hb", daemon=True)

    def _run(self) -> None:
        try:
            self.node.run(self.stop)
        except BaseException as e:  # reported by alive()
            self.error.append(e)

    def start(self) -> None:
        self.thread.start()
        assert wait_for(lambda: self.node.sub is not None, 5)
        # the slow joiner: heartbeats until the node hears them
        ok = wait_for(lambda: self._probe(), 5, step_s=0.02)
        assert ok, "the operator node never received anything"
        time.sleep(0.2)
        self.sent = self.received()  # probes sent before the subscription arrived were lost
        self._beat_thread.start()

    def _beat(self) -> None:
        """What a live robot does between changes: confirm the stimulus at 20 Hz."""
        while not self._beating.wait(0.05):
            self.heartbeat()

    def _probe(self) -> bool:
        self.heartbeat()
        return self.received() > 0

    def received(self) -> int:
        sub = self.node.sub
        return 0 if sub is None else sub.received

    def rejected(self) -> int:
        sub = self.node.sub
        return 0 if sub is None else sub.rejected_total

    def alive(self) -> bool:
        return self.thread.is_alive() and not self.error

    def send_raw(self, data: bytes) -> None:
        with self._send_lock:  # the heartbeat thread shares the socket
            self.pub.send(data)
            self.sent += 1

    def heartbeat(self) -> None:
        self.hb_seq += 1
        cur = self.current
        now = now_ns()
        self.send_raw(
            encode(
                Heartbeat(
                    seq=self.hb_seq,
                    t_send_ns=now,
                    node="robot",
                    state="ok",
                    stimulus_seq=None if cur is None else cur.seq,
                    t_capture_ns=None if cur is None else now,
                )
            )
        )

    def show(self, pattern: int | None) -> Stimulus:
        """Send a new good stimulus: one pattern at 4 N, or nothing held."""
        self.stim_seq += 1
        now = now_ns()
        stim = np.zeros((3, 3), np.float32) if pattern is None else stimulus_for(pattern)
        msg = Stimulus(
            seq=self.stim_seq,
            t_send_ns=now,
            t_capture_ns=now,
            frame_seq=self.stim_seq,
            mode="direct",
            contact=pattern is not None,
            stimulus=stim,
        )
        self.send_raw(encode(msg))
        self.current = msg
        return msg

    def sync(self, timeout_s: float = 10.0) -> bool:
        """Wait until the node has read, and acted on, everything sent so far."""
        return handled_all(self, timeout_s)

    def goal_reached(self, target: np.ndarray) -> bool:
        last = self.node.written_goals
        return last is not None and np.array_equal(last, target)

    def servo_violations(self) -> list[str]:
        cal = self.bus.calibration
        bad = []
        if self.bus.status()["refused"]:
            bad.append(f"the bus refused {self.bus.status()['refused']} writes")
        lo = {s.id: s.min_counts for s in cal.servos}
        hi = {s.id: s.max_counts for s in cal.servos}
        for rec in self.bus.records:
            for sid, c in rec.goals.items():
                if isinstance(c, bool) or not isinstance(c, int) or not lo[sid] <= c <= hi[sid]:
                    bad.append(f"servo {sid} goal {c!r}")
        return bad

    def close(self) -> None:
        self._beating.set()
        if self._beat_thread.is_alive():
            self._beat_thread.join(timeout=2)
        self.stop.set()
        self.thread.join(timeout=10)
        self.pub.close(0)
        self.cmd_sub.close(0)
        self.ctx.term()


# ------------------------------------------------------------------ robot
def _hold_script() -> GraspScript:
    return GraspScript(
        grasps=[
            GraspStep(pattern=p, grip_level=20, ramp_s=0.2, hold_s=1.0, release_s=0.1, pause_s=0.2)
            for p in (6, 3, 9, 0)
        ],
        loop=True,
        start_delay_s=0.1,
    )


class RobotRig:
    """A robot node with a scripted sensor and recording devices; this test is its operator."""

    def __init__(self) -> None:
        rc = RobotConfig()
        rc.render.mode = "mask_ground_truth"
        rc.link.telemetry_endpoint = "tcp://127.0.0.1:*"
        rc.link.command_endpoint = "tcp://127.0.0.1:*"
        self.arm = MemoryArm()
        self.gripper = MemoryGripper()
        sensor = ScriptedTactileSensor(ScriptedTactileConfig(script=_hold_script(), seed=11))
        self.node = RobotNode(rc, sensor, gripper=self.gripper, arm=self.arm)
        self.stop = threading.Event()
        self.error: list[BaseException] = []
        self.thread = threading.Thread(target=self._run, name="fuzz-robot", daemon=True)
        self.ctx = zmq.Context()
        self.sent = 0
        self.hb_seq = 0
        self.cmd_seq = 0
        self.my_heartbeats: dict[int, int] = {}  # t_send_ns -> seq of the good heartbeats
        self.robot_heartbeat: tuple[int | None, int | None] = (None, None)  # newest, for echoes
        self.session = 4242  # the good operator's boot id (commands and heartbeats)
        self.robot_session: int | None = None  # the robot run heard, echoed on what we send
        self.echoed = 0
        self.telemetry: dict[str, int] = {"stimulus": 0, "heartbeat": 0, "frame": 0}
        self._lock = threading.Lock()  # my_heartbeats and hb_seq, shared with the beat thread
        self._count_lock = threading.Lock()

    def _run(self) -> None:
        try:
            self.node.run(self.stop)
        except BaseException as e:  # reported by alive()
            self.error.append(e)

    def start(self) -> None:
        self.thread.start()
        assert wait_for(lambda: self.node.sub is not None, 5)
        cmd_ep = self.node.sub.endpoint
        self.good = _pub(self.ctx, cmd_ep, bind=False)
        self.evil = _pub(self.ctx, cmd_ep, bind=False)
        self.beat = _pub(self.ctx, cmd_ep, bind=False)
        self.tel = _sub(self.ctx, self.node.pub.endpoint, bind=False)
        # every publisher must be connected before counting: probe each until it is heard
        for sock in (self.good, self.evil, self.beat):
            before = self.received()

            def probe(sock=sock, before=before) -> bool:
                self._send(sock, self._heartbeat())
                return self.received() > before

            assert wait_for(probe, 5, step_s=0.02), "the robot node never heard a publisher"
        time.sleep(0.2)
        self._count_from_here()  # probes sent before the connection was up were lost
        # the operator's heartbeats at 20 Hz come from their own thread, as in the real node,
        # so the deadman sees a live operator whatever the fuzzing thread is doing
        self._beating = threading.Event()
        self._beat_thread = threading.Thread(target=self._beat, name="fuzz-heartbeats", daemon=True)
        self._beat_thread.start()
        # the robot moves nothing before a heartbeat round trip has given it our clock
        assert wait_for(lambda: (self.read_telemetry(), self.node.clock.is_synced)[1], 5)
        self._count_from_here()

    def _count_from_here(self) -> None:
        """Count what is sent from what the node has read so far.

        Under the lock that ``_send`` holds across a send and its count: a beat
        the node read before the beat thread counted it was counted twice here
        (in ``received`` and then in ``sent``), and ``sync`` then waited for
        one message more than was ever sent.
        """
        with self._count_lock:
            self.sent = self.received()

    def _beat(self) -> None:
        while not self._beating.wait(0.05):
            self._send(self.beat, self._heartbeat())

    def received(self) -> int:
        sub = self.node.sub
        return 0 if sub is None else sub.received

    def rejected(self) -> int:
        sub = self.node.sub
        return 0 if sub is None else sub.rejected_total

    def alive(self) -> bool:
        return self.thread.is_alive() and not self.error

    def _send(self, sock: zmq.Socket, data: bytes) -> None:
        with self._count_lock:  # a send and its count are one step for _count_from_here
            sock.send(data)
            self.sent += 1

    def send_evil(self, data: bytes) -> None:
        self._send(self.evil, data)

    def _heartbeat(self) -> bytes:
        with self._lock:
            self.hb_seq += 1
            t = now_ns()
            self.my_heartbeats[t] = self.hb_seq
            if len(self.my_heartbeats) > 10_000:
                self.my_heartbeats.pop(next(iter(self.my_heartbeats)))
            seq = self.hb_seq
            echo_send, echo_recv = self.robot_heartbeat
        return encode(
            Heartbeat(
                seq=seq,
                t_send_ns=t,
                node="operator",
                state="ok",
                echo_t_send_ns=echo_send,
                echo_t_recv_ns=echo_recv,
                session=self.session,
                echo_session=self.robot_session,
            )
        )

    def command(self, action: str, **kw: Any) -> None:
        self.cmd_seq += 1
        cmd = Command(
            seq=self.cmd_seq,
            t_send_ns=now_ns(),
            action=action,
            session=self.session,
            echo_session=self.robot_session,
            **kw,
        )
        self._send(self.good, encode(cmd))

    def read_telemetry(self) -> None:
        while self.tel.poll(0):
            msg = decode(self.tel.recv())
            kind = type(msg).TYPE
            self.telemetry[kind] += 1
            with self._lock:
                mine = isinstance(msg, Heartbeat) and msg.echo_t_send_ns in self.my_heartbeats
                if isinstance(msg, Heartbeat):  # echoed in ours: the robot learns our clock
                    self.robot_heartbeat = (msg.t_send_ns, now_ns())
                    self.robot_session = msg.session  # echoed: our messages are of its run
            self.echoed += mine

    def sync(self, timeout_s: float = 10.0) -> bool:
        """Wait until the node has read, and acted on, everything sent so far."""
        return handled_all(self, timeout_s)

    def close(self) -> None:
        self._beating.set()
        self._beat_thread.join(timeout=2)
        self.stop.set()
        self.thread.join(timeout=10)
        for s in (self.good, self.evil, self.beat, self.tel):
            s.close(0)
        self.ctx.term()


# ------------------------------------------------------- mutant producer
class MutantStream:
    """Mutants made in another process, so the other core does the generating."""

    def __init__(self, seed: int, total: int, kinds: list[str] | None = None, batch: int = 500):
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe(duplex=False)
        self._proc = ctx.Process(
            target=produce, args=(child, seed, kinds, total, batch), daemon=True
        )
        self._proc.start()
        child.close()

    def __iter__(self):
        while True:
            data = self._conn.recv_bytes()
            if not data:
                return
            yield msgpack.unpackb(data, raw=False)

    def close(self) -> None:
        if self._proc.is_alive():
            self._proc.terminate()  # it may be blocked writing batches nobody will read
        self._proc.join(timeout=5)
        self._conn.close()


def finite_all(values: Any) -> bool:
    return all(math.isfinite(float(v)) for v in values)
