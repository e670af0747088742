"""The operator node: stimuli in, LinkGlide servo goals out; commands back to the robot.

Event-driven on the socket, paced by a 60 Hz deadline: a new stimulus is
rendered as soon as it arrives (at most one servo write per half cycle), and
the rate limiter keeps stepping toward the target on every cycle in between.
A stimulus is rendered only while fresh: one older than ``stale_after_ms``
(capture time mapped through the estimated clock offset) lifts every
linkage off the palm, and rendering resumes by itself when fresh data does.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import json
import logging
import math
import os
import queue
import secrets
import threading
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import zmq

from common.clock import Clock, Periodic, now_ns
from common.clock_sync import ClockSync
from common.codec import DecodeError, check_robot_name, encode, name_prefix
from common.devices import build_device
from common.errors import ConfigError, DeviceError
from common.link_stats import LinkStats
from common.logs import BurstLog
from common.messages import (
    SESSION_LOW_MASK,
    Command,
    Heartbeat,
    Stimulus,
    TactileFrame,
    VideoSignal,
)
from common.recording import NullRecorder, Recorder
from common.security import check_endpoint, client_options
from common.tactile import matches_pattern
from common.transport import (
    Link,
    Publisher,
    Receiver,
    Sender,
    Subscriber,
    link_health,
    make_context,
)
from operator_side.config import OperatorConfig
from operator_side.renderer import LinkGlideRenderer
from operator_side.servos.base import ServoBus
from operator_side.servos.calibration import LinkGlideCalibration
from operator_side.telemetry_gate import REFUSALS as TELEMETRY_REFUSALS
from operator_side.telemetry_gate import UNPROVEN, TelemetryGate

log = logging.getLogger(__name__)

#: longest a video signal waits for the robot to show it hears us before it goes anyway
VIDEO_HOLD_NS = 3_000_000_000

#: the loop woke this much later than it was due: the machine starved it, and the palm's
#: staleness could not act meanwhile (logged with when it was due and woke, on the monotonic
#: clock, and counted in ``late_wakes``, its lateness summed in ``late_wake_ms``)
LATE_WAKE_NS = 100_000_000
RESTART_SEQ_GAP = 1000  # a sequence number this far back means the robot restarted
#: the clean stop's longest wait for the retract pose before torque off (a pressing linkage
#: is a few degrees from it: about 0.1 s at the servos' speed)
LIFT_ARRIVAL_S = 0.2


@dataclass
class Snapshot:
    """What the live views show; a copy, safe to read from another thread."""

    link_state: str
    stimulus: np.ndarray | None
    pattern: int | None
    confidence: float | None
    grip_level: int | None
    frame: np.ndarray | None
    goal_counts: np.ndarray
    goal_angles: np.ndarray
    age_ms: float | None
    stats: dict[str, float]
    robot_stats: dict[str, float]
    #: with a signing key: who holds the robot's control lease (``OperatorNode.control_view``)
    control: dict[str, Any] | None = None

    def as_json(self) -> dict[str, Any]:
        """Plain JSON data (an operator node in another process shows it: its status file)."""
        out = dataclasses.asdict(self)
        for name in (*_SNAPSHOT_ARRAYS, "goal_angles"):
            value = out[name]
            out[name] = None if value is None else np.asarray(value).tolist()
        return json.loads(json.dumps(out, default=_plain))

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Snapshot:
        fields = dict(data)
        for name, dtype in _SNAPSHOT_ARRAYS.items():
            if fields[name] is not None:
                fields[name] = np.array(fields[name], dtype=dtype)
        fields["goal_angles"] = np.array(fields["goal_angles"], dtype=np.float64)
        return cls(**fields)


_SNAPSHOT_ARRAYS = {"stimulus": np.float32, "frame": np.float32, "goal_counts": np.int64}


def _plain(value: Any) -> Any:
    """A NumPy scalar or bytes (a key) as JSON."""
    if isinstance(value, bytes):
        return value.hex()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"{type(value).__name__} is not JSON")


@dataclass
class _PendingGripper:
    action: str
    grip_level: int | None
    seq: int
    deadline_ns: int
    resends: int


class OperatorNode:
    def __init__(
        self,
        config: OperatorConfig,
        servos: ServoBus,
        *,
        calibration: LinkGlideCalibration | None = None,
        ctx: zmq.Context | None = None,
        recorder: Recorder | None = None,
        now: Clock = now_ns,
        link: Link | None = None,
    ) -> None:
        """``now`` and ``link``: the clock and the link, handed in to replay or bench the node.

        ``link`` is the transport (``pub``, ``sub``); ``self.link`` keeps its statistics.
        """
        self.config = config
        self.servos = servos
        self.now = now
        self.recorder = recorder or NullRecorder()
        self._recording = not isinstance(self.recorder, NullRecorder)
        self._use_calibration(calibration or servos.calibration or LinkGlideCalibration())
        self._own_ctx = ctx is None
        self.ctx = ctx or make_context()
        self.clock = ClockSync()
        #: loss, latency, jitter and staleness of the stimulus stream
        self.link = LinkStats(clock=self.clock)
        self.counters: Counter[str] = Counter()
        self.latencies_ms: collections.deque[float] = collections.deque(
            maxlen=config.latency_window
        )
        self.link_state = "down"
        #: (monotonic ns, new state) of the latest link state changes
        self.link_changes: collections.deque[tuple[int, str]] = collections.deque(maxlen=256)
        # each with when the operator issued it (our clock): a jog that waited too long is dropped
        self._commands: queue.SimpleQueue[tuple[int, Command | VideoSignal]] = queue.SimpleQueue()
        #: called on the node's thread with each video signal the robot sends (the dashboard)
        self.video_signal_handler: Callable[[VideoSignal], None] | None = None
        self._vsig_seq = 0
        #: (queued at, signal): video signals held until the robot is known to hear us
        self._held_signals: collections.deque[tuple[int, VideoSignal]] = collections.deque()
        self._wake_r, self._wake_w = os.pipe()  # send_command wakes a sleeping loop
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        self._lock = threading.Lock()
        self._stim: Stimulus | None = None
        self._stim_local_capture_ns: int | None = None  # newest confirmation, local clock
        self._pending_latency_capture: int | None = None
        self._frame: TactileFrame | None = None
        self._robot_stats: dict[str, float] = {}
        self._hb_seq = 0
        self._cmd_seq = 0
        #: this run's boot id, on every message we send: the robot checks seq increases within it
        self._session = secrets.randbits(63) or 1
        #: the robot run (its session) we last heard, echoed on everything we send: it proves
        #: to a robot that restarted that our messages are of its run, not recorded before
        self._robot_session: int | None = None
        #: the newest gripper command until the robot's heartbeat confirms it
        self._gripper_pending: _PendingGripper | None = None
        self._goal: list[int] = self.renderer.retract_goals  # six counts, ids 1..6
        self._latency_cache: tuple[int, dict[str, float]] = (0, {})
        self._goal_key: int | None = None  # stimulus seq the goal was computed for
        self._written: list[int] | None = None  # the goals last sent to the bus
        self._last_step_ns = 0
        self._handed_link = link is not None
        self.pub: Sender | None = link.pub if link is not None else None
        self.sub: Receiver | None = link.sub if link is not None else None
        self._sockets_opened_ns = 0
        self._last_rx_ns = 0
        #: the send time of the robot's newest stimulus or heartbeat, on our clock
        self._robot_heard_ns: int | None = None
        self._blind_log = BurstLog(log, "jog held: no fresh telemetry, we cannot see the arm")
        self._late_log = BurstLog(log, "jog dropped: it waited too long on this busy PC")
        self._rejected_before = 0  # rejections counted by sockets since reopened
        link_cfg = config.link
        try:
            self.robot_name = check_robot_name(link_cfg.robot_name) if link_cfg.robot_name else b""
        except DecodeError as e:
            raise ConfigError(f"operator link.robot_name: {e}") from None
        self.signer = None
        if link_cfg.signing_key_file is not None:
            from common.signing import load_signer  # cryptography only when signing

            self.signer = load_signer(link_cfg.signing_key_file)
        #: the robot's public key: telemetry signed by anyone else (or unsigned) is dropped
        self.robot_key: bytes | None = None
        if self.robot_name and link_cfg.robot_key_file is None and not link_cfg.unsigned_stream:
            raise ConfigError(
                "operator link.robot_name is set (through a relay), so the robot's stream must "
                "be signed: set link.robot_key_file to the robot's NAME.sign (`deepxpalm keys "
                "robot`), or link.unsigned_stream = true to accept what a relay could forge"
            )
        if link_cfg.robot_key_file is not None:
            from common.signing import load_public_key

            self.robot_key = load_public_key(link_cfg.robot_key_file)
        #: with the robot's key: its signed telemetry is believed once, fresh, from its run
        self.telemetry_gate: TelemetryGate | None = None
        if self.robot_key is not None:
            self.telemetry_gate = TelemetryGate(
                self.clock,
                round(link_cfg.max_telemetry_age_ms * 1e6),
                self.signer.public if self.signer is not None else None,
            )
        #: the key holding the robot's control lease, as its newest heartbeat says
        self.lease_holder: bytes | None = None
        #: the key waiting for the lease, as the robot's newest heartbeat says
        self.lease_pending: bytes | None = None
        self._hb_turn = 0
        self._next_lease_request_ns = 0
        self._forged_log = BurstLog(log, "telemetry dropped: not signed by the robot's key")
        #: one per reason, so a replay's first example is not hidden behind another reason's
        self._refusal_logs = {
            reason: BurstLog(log, "signed telemetry refused (replay window)")
            for reason in TELEMETRY_REFUSALS
        }

    def _use_calibration(self, calibration: LinkGlideCalibration) -> None:
        self.calibration = calibration
        self.renderer = LinkGlideRenderer(self.config.renderer, calibration)
        self._servo_ids = [int(i) for i in calibration.ids]

    # ---------------------------------------------------------- commands
    def send_command(
        self,
        action: str,
        grip_level: int | None = None,
        velocity: tuple[float, ...] | None = None,
        grantee: bytes | None = None,
        age_ms: float = 0.0,
    ) -> None:
        """Queue a command for the robot; thread-safe (sockets stay on the loop thread).

        ``arm_stop`` is a STOP: it latches on the robot, which then refuses
        every jog (from anyone) until the lease holder sends ``arm_resume``;
        ``arm_jog_end`` ends a jog without latching (docs/protocol.md).
        ``age_ms``: how long ago the operator issued it (a page's jog that sat in
        a queue before it reached us); a jog older than ``jog_max_age_ms`` when
        its turn comes is dropped.
        """
        issued = self.now() - round(max(age_ms, 0.0) * 1e6) if math.isfinite(age_ms) else 0
        self._commands.put(
            (
                issued,
                Command(
                    seq=0,
                    t_send_ns=0,
                    action=action,
                    grip_level=grip_level,
                    velocity=velocity,
                    grantee=grantee,
                ),
            )
        )
        with contextlib.suppress(BlockingIOError, OSError):
            os.write(self._wake_w, b"c")  # the loop may be asleep until a deadline

    def send_video_signal(self, kind: str, viewer: int, sdp: str | None = None) -> None:
        """Queue a WebRTC offer or bye for the robot's video server; thread-safe.

        It travels the command link (signed, through the relay when there is
        one), so video needs no connection of its own to the robot PC.
        """
        signal = VideoSignal(seq=0, t_send_ns=0, kind=kind, viewer=viewer, sdp=sdp)
        self._commands.put((self.now(), signal))
        with contextlib.suppress(BlockingIOError, OSError):
            os.write(self._wake_w, b"v")

    def mark_episode(self, kind: str, task: str | None = None, source: str = "dashboard") -> bool:
        """Record the operator's mark on the episode in progress; thread-safe.

        ``kind`` is failed, discard or success (common/episode_marks.py); the
        export applies it to the episode it falls in. Nothing goes to the
        robot. False when this node is not recording: the mark would be lost.
        """
        from common.episode_marks import CHANNEL, check_mark

        problem = check_mark(kind, task)
        if problem is not None:
            raise ValueError(problem)
        if not self._recording:
            return False
        record: dict[str, Any] = {"kind": kind, "source": source}
        if task is not None:
            record["task"] = task.strip()
        self.recorder.write(CHANNEL, self.now(), record)
        return True

    # --------------------------------------------------------------- run
    def run(self, stop: threading.Event, duration_s: float | None = None) -> None:
        if self._handed_link:
            raise RuntimeError("a node handed a link is driven by its caller; run() opens its own")
        link = self.config.link
        if not self.servos.is_connected:
            self.servos.connect()
        bus_calibration = self.servos.calibration
        if bus_calibration is not None and bus_calibration is not self.calibration:
            self._use_calibration(bus_calibration)  # the bus's limits are the ones enforced
        try:
            for endpoint in (link.telemetry_endpoint, link.command_endpoint):
                check_endpoint(endpoint, link.security)
            self._open_sockets()
            self.servos.set_torque(True)
            self._write(self.renderer.retract_goals)
            log.info(
                "operator node up: telemetry %s, commands %s",
                link.telemetry_endpoint,
                link.command_endpoint,
            )
            self._loop(stop, duration_s)
        finally:
            try:
                if self.servos.is_connected:
                    self._lift_off_now()
            finally:
                if self.sub is not None:
                    self.sub.close()
                if self.pub is not None:
                    self.pub.close()
                self.servos.disconnect()
                if self._own_ctx:
                    self.ctx.term()

    @property
    def loop_turns(self) -> int:
        """Turns of the loop so far (at least one per heartbeat period, robot or not): systemd's
        watchdog is pinged only while this grows (``common.sd_notify``), so a frozen or stuck
        loop is ended and the palm lifted by the unit's ExecStopPost."""
        return self.counters["wakeups"]

    @property
    def arm_stop_latched(self) -> bool:
        """Whether the robot's newest heartbeat says a STOP holds the arm (anyone's stop)."""
        return bool(self._robot_stats.get("arm_stop_latched"))

    @property
    def is_controller(self) -> bool:
        """Whether the robot's newest heartbeat names our key as the lease holder."""
        return self.signer is not None and self.lease_holder == self.signer.public

    def _topics(self) -> tuple[bytes, ...]:
        """What we subscribe to: one robot's stimuli and heartbeats, and frames if wanted."""
        name = self.robot_name
        if not name:
            return (b"",)
        topics = [name_prefix(Stimulus.TOPIC, name), name_prefix(Heartbeat.TOPIC, name)]
        if self.config.link.want_frames:
            topics.append(name_prefix(TactileFrame.TOPIC, name))
        if self.video_signal_handler is not None:
            topics.append(name_prefix(VideoSignal.TOPIC, name))
        return tuple(topics)

    def _open_sockets(self) -> None:
        link = self.config.link
        opts = client_options(link.security)
        self.sub = Subscriber(
            self.ctx,
            link.telemetry_endpoint,
            bind=False,
            sock_opts=opts,
            name="operator telemetry",
            topics=self._topics(),
            expect_name=self.robot_name,
            reconnect=True,  # opened again at once if libzmq gives up (a protocol error)
            link_name="telemetry",
        )
        self.pub = Publisher(
            self.ctx,
            link.command_endpoint,
            bind=False,
            sock_opts=opts,
            name=self.robot_name,
            signer=self.signer,
            reconnect=True,
            link_name="commands",
        )
        self.sub.poller.register(self._wake_r, zmq.POLLIN)
        self._sockets_opened_ns = self.now()

    def _reopen_sockets_if_silent(self, now: int) -> None:
        """Open both sockets again after a long silence.

        libzmq never reconnects a connecting socket after a protocol error (an
        oversized or malformed frame from the peer), so a link that went silent
        may be dead on our side only; a fresh socket costs nothing if it was not.
        """
        quiet_since = max(self._last_rx_ns, self._sockets_opened_ns)
        if (now - quiet_since) / 1e6 < self.config.link.reopen_after_ms:
            return
        log.info("no telemetry for %.1f s: opening the sockets again", (now - quiet_since) / 1e9)
        rejected = self.sub.rejected_total
        self.sub.close()
        self.pub.close()
        self._open_sockets()
        self._rejected_before += rejected
        self.counters["sockets_reopened"] += 1

    def _loop(self, stop: threading.Event, duration_s: float | None) -> None:
        link = self.config.link
        period = round(1e9 / self.config.renderer.control_rate_hz)
        heartbeat = Periodic(link.heartbeat_rate_hz, link.heartbeat_early_ms / 1e3)
        next_control = self.now()
        t_end = None if duration_s is None else self.now() + round(duration_s * 1e9)
        while not stop.is_set() and (t_end is None or self.now() < t_end):
            due = min(next_control, heartbeat.deadline_ns)
            ready = self.sub.ready((due - self.now()) / 1e9)
            self.counters["wakeups"] += 1
            woke = self.now()
            if woke - due > LATE_WAKE_NS:  # at most ten a second, by its definition
                self.counters["late_wakes"] += 1
                self.counters["late_wake_ms"] += round((woke - due) / 1e6)
                log.warning(
                    "the loop woke %.0f ms late (a starved process: the palm cannot lift "
                    "meanwhile, its staleness limit is %.0f ms); due_ns=%d woke_ns=%d",
                    (woke - due) / 1e6,
                    link.stale_after_ms,
                    due,
                    woke,
                )
            changed = self.receive() if self.sub.sock in ready else False
            now = self.now()
            if changed or now >= next_control:
                # Rendered as soon as something changed; otherwise the loop sleeps
                # until the goal moves, the data would go stale, or a heartbeat.
                self.control_step(now, period)
                next_control = self._next_control_ns(now, period)
            if heartbeat.due(now):
                if self._heartbeat_wanted():
                    self._send_heartbeat()
                heartbeat.done(now)
            self._maybe_request_control(now)
            if self._wake_r in ready:
                self._drain_wake_pipe()
            self.flush_commands(now)
            self._reopen_sockets_if_silent(now)

    def _next_control_ns(self, now: int, period: int) -> int:
        """When the next control step is needed if no message arrives first."""
        if self._written is not None and self._written != self._goal:
            return now + period  # still stepping toward the goal
        captured = self._stim_local_capture_ns
        if self.link_state == "ok" and captured is not None:
            return captured + round(self.config.link.stale_after_ms * 1e6) + 1
        return now + 10 * period  # lifted and idle: messages wake the loop

    # ----------------------------------------------------------- receive
    def receive(self) -> bool:
        """Drain the socket; True when a new stimulus arrived."""
        new = False
        robot_key, gate = self.robot_key, self.telemetry_gate
        for msg, t_recv in self.sub.drain():
            if robot_key is not None and msg.signer != robot_key:
                # not from our robot: a relay (or anyone on the path) cannot make the palm move
                what = "telemetry_unsigned" if msg.signer is None else "telemetry_forged"
                self.counters[what] += 1
                self._forged_log(f"{type(msg).__name__}: {what}")
                continue
            if gate is not None and not self._admitted(gate, msg, t_recv):
                continue  # ours, but not now: a replay, an old run, or too old to act on
            self._last_rx_ns = t_recv
            if isinstance(msg, Stimulus):
                new |= self._on_stimulus(msg, t_recv)
            elif isinstance(msg, Heartbeat):
                self._on_heartbeat(msg, t_recv)
                new |= self.link_state != "ok"  # it may confirm a stimulus again
            elif isinstance(msg, TactileFrame):
                with self._lock:
                    self._frame = msg
            elif isinstance(msg, VideoSignal) and self.video_signal_handler is not None:
                self.video_signal_handler(msg)
            else:
                self.counters["messages_unexpected"] += 1
        self.counters["decode_errors"] = self._rejected_before + self.sub.rejected_total
        return new

    def _admitted(self, gate: TelemetryGate, msg: Any, t_recv: int) -> bool:
        """Whether the telemetry gate lets the robot's signed message through; counted if not."""
        believed = gate.session
        refusal = gate.admit(msg, t_recv)
        if refusal is None:
            if gate.session != believed:
                self.counters["telemetry_sessions"] += 1
                retired = "" if believed is None else f", its run {believed:016x} retired"
                log.info(
                    "robot run %016x believed: a heartbeat answered ours%s (%d refused so far "
                    "as unproven)",
                    gate.session,
                    retired,
                    self.counters[UNPROVEN],
                )
            return True
        self.counters[refusal] += 1
        if refusal == UNPROVEN:
            if isinstance(msg, Heartbeat) and msg.session is not None:
                # Echo the run we hear (signed by our robot) before we believe it: the robot
                # acts on our heartbeats only once they echo its run, and only then answers
                # them, which is what proves the run to us. Nothing else is taken from it.
                self._robot_session = msg.session
            return False  # they come at every start, until the robot answers us
        session = getattr(msg, "session", None)
        if session is None:
            self._refusal_logs[refusal](
                f"{type(msg).__name__} seq {msg.seq} signed without a session: the robot node "
                "predates the replay window (docs/protocol.md); update it"
            )
            return False
        offset = self.clock.offset_ns
        age = (
            "" if offset is None else f", sent {(t_recv + offset - msg.t_send_ns) / 1e6:.0f} ms ago"
        )
        self._refusal_logs[refusal](
            f"{type(msg).__name__} {refusal}: run {session:016x}, seq {msg.seq}{age}"
        )
        return False

    def _heard_robot(self, t_send_ns: int, t_recv: int) -> None:
        """The robot was alive at ``t_send_ns``: a backlog delivered late does not count as now."""
        local = self._to_local(t_send_ns, t_recv)
        if self._robot_heard_ns is None or local > self._robot_heard_ns:
            self._robot_heard_ns = local

    def sees_robot(self, now: int) -> bool:
        """Whether the robot's telemetry is fresh enough to steer by (``jog_blind_after_ms``)."""
        heard = self._robot_heard_ns
        return heard is not None and (now - heard) / 1e6 <= self.config.link.jog_blind_after_ms

    def _on_stimulus(self, msg: Stimulus, t_recv: int) -> bool:
        self.link.on_message(msg.seq, msg.t_send_ns, t_recv)
        self._heard_robot(msg.t_send_ns, t_recv)
        last = self._stim
        if (
            last is not None
            and last.session == msg.session  # a new run numbers from 1 again
            and last.seq - RESTART_SEQ_GAP < msg.seq <= last.seq
        ):
            self.counters["stimuli_out_of_order"] += 1
            return False
        self.counters["stimuli_received"] += 1
        if self._recording:
            self.recorder.write("operator/stimulus", t_recv, {"seq": msg.seq, "wire": encode(msg)})
        local_capture = self._to_local(msg.t_capture_ns, t_recv)
        with self._lock:
            self._stim = msg
            self._stim_local_capture_ns = local_capture
        self._pending_latency_capture = local_capture
        if msg.sim_truth_pattern is not None and msg.contact:
            self.counters["stimuli_with_truth"] += 1
            if matches_pattern(msg.stimulus, msg.sim_truth_pattern):
                self.counters["stimuli_matching_truth"] += 1
        return True

    def _heartbeat_wanted(self) -> bool:
        """Every due heartbeat, unless we are a signed observer (``observer_heartbeat_rate_hz``)."""
        link = self.config.link
        self._hb_turn += 1
        if self.signer is None or self.is_controller or link.request_control:
            return True
        if self.lease_pending == self.signer.public:
            return True  # asked: the robot's deadman will count from us as soon as it grants
        every = max(1, round(link.heartbeat_rate_hz / max(link.observer_heartbeat_rate_hz, 1e-3)))
        return self._hb_turn % every == 0

    def _maybe_request_control(self, now: int) -> None:
        """``request_control``: ask while nobody holds the lease (refused until clocks sync)."""
        if not self.config.link.request_control or self.signer is None:
            return
        if self.lease_holder is not None or now < self._next_lease_request_ns:
            return
        self._next_lease_request_ns = now + 250_000_000
        self.counters["lease_requests_sent"] += 1
        self.send_command("lease_request")

    def _on_heartbeat(self, msg: Heartbeat, t_recv: int) -> None:
        if msg.node != "robot":
            return
        self.counters["heartbeats_received"] += 1
        echo_send, echo_recv = msg.echo_t_send_ns, msg.echo_t_recv_ns
        if msg.echo_signer is not None and (
            self.signer is None or msg.echo_signer != self.signer.public
        ):
            echo_send = echo_recv = None  # it answers another operator's heartbeat
        self.clock.on_heartbeat(msg.t_send_ns, echo_send, echo_recv, t_recv)
        self._heard_robot(msg.t_send_ns, t_recv)
        if msg.session is not None:
            self._robot_session = msg.session
        was = self.is_controller
        self.lease_holder = msg.controller
        self.lease_pending = msg.lease_pending
        if self.is_controller != was:
            self.counters["lease_gained" if not was else "lease_lost"] += 1
            log.info("control lease %s", "ours" if not was else "no longer ours")
        self._robot_stats = msg.stats
        self._confirm_gripper(msg.stats)
        stim = self._stim
        if stim is not None and msg.stimulus_seq == stim.seq and msg.t_capture_ns is not None:
            local = self._to_local(msg.t_capture_ns, t_recv)
            with self._lock:
                if self._stim_local_capture_ns is None or local > self._stim_local_capture_ns:
                    self._stim_local_capture_ns = local

    def _to_local(self, t_remote_ns: int, t_recv_ns: int) -> int:
        """A robot timestamp on our clock; before the offset is known, the receive time."""
        if not self.clock.is_synced:
            return t_recv_ns
        return min(self.clock.to_local(t_remote_ns), t_recv_ns)

    # ----------------------------------------------------------- control
    def fresh_stimulus(self, now: int) -> tuple[np.ndarray | None, float | None]:
        stim, captured = self._stim, self._stim_local_capture_ns
        if stim is None or captured is None:
            return None, None
        age_ms = (now - captured) / 1e6
        if age_ms > self.config.link.stale_after_ms:
            return None, age_ms
        return stim.stimulus, age_ms

    def control_step(self, now: int, period_ns: int) -> None:
        stimulus, age_ms = self.fresh_stimulus(now)
        state = "ok" if stimulus is not None else ("stale" if self._stim is not None else "down")
        if state != self.link_state:
            log.info(
                "link %s -> %s (age %s ms)",
                self.link_state,
                state,
                "n/a" if age_ms is None else f"{age_ms:.0f}",
            )
            if state != "ok":
                self.counters["lift_offs"] += 1
            self.link_state = state
            self.link_changes.append((now, state))
        key = self._stim.seq if stimulus is not None else None
        if key != self._goal_key:  # IK only when what is rendered changed
            self._goal = self.renderer.goals_for(stimulus)
            self._goal_key = key
            self.counters["targets_computed"] += 1
        fraction = 1.0 if not self._last_step_ns else (now - self._last_step_ns) / period_ns
        current = self._written if self._written is not None else self.renderer.retract_goals
        nxt = self.renderer.step_goals(current, self._goal, fraction)
        self._last_step_ns = now
        if nxt != self._written:
            self._write(nxt)
            if self._pending_latency_capture is not None and stimulus is not None:
                self.latencies_ms.append((self.now() - self._pending_latency_capture) / 1e6)
                self.counters["latency_samples"] += 1
        self._pending_latency_capture = None  # a stimulus that moved nothing has no latency

    def _write(self, counts: list[int]) -> None:
        self.servos.write_goals(dict(zip(self._servo_ids, counts, strict=True)))
        self._written = counts
        if self._recording:
            written = np.array(counts, dtype=np.int64)
            self.recorder.write(
                "operator/servo_goals",
                self.now(),
                {
                    "ids": self.calibration.ids,
                    "counts": written,
                    "angles": self.calibration.counts_to_angles(written),
                },
            )
        self.counters["servo_writes"] += 1

    def rewrite_next(self) -> None:
        """Write the next control step's goals even if unchanged (benchmarks force each one)."""
        self._written = None

    @property
    def written_goals(self) -> list[int] | None:
        """The goal counts last written to the servos (None before the first write)."""
        return self._written

    @property
    def last_stimulus(self) -> Stimulus | None:
        """The newest stimulus received, fresh or not."""
        return self._stim

    def _lift_off_now(self) -> None:
        """On shutdown: straight to the retract pose (a lift is always safe), and torque stays
        on until the servos are there (at most ``LIFT_ARRIVAL_S``): let go mid-way, a linkage
        stays where it was, maybe on the palm."""
        self._write(self.renderer.retract_goals)
        goals = dict(zip(self._servo_ids, self.renderer.retract_goals, strict=True))
        try:
            away = self.servos.wait_for_arrival(goals, LIFT_ARRIVAL_S)
        except DeviceError as e:  # the bus failed on the way out: torque goes off regardless
            log.warning("lift on the way out: positions unreadable (%s); torque off", e)
            return
        if away:
            log.warning(
                "lift on the way out: servos %s not at the retract pose after %.0f ms (at %s); "
                "torque off",
                sorted(away),
                LIFT_ARRIVAL_S * 1e3,
                away,
            )

    # --------------------------------------------------------- heartbeat
    def _send_heartbeat(self) -> None:
        self._hb_seq += 1
        if self._recording:
            est = self.clock.estimate()
            self.recorder.write(
                "operator/link",
                self.now(),
                {
                    "state": self.link_state,
                    "clock_offset_ns": None if est is None else est.offset_ns,
                    "clock_uncertainty_ns": None if est is None else est.uncertainty_ns,
                    **self.stats(),
                },
            )
        echo_send, echo_recv = self.clock.echo_fields()
        t_send = self.now()
        if self.telemetry_gate is not None:
            self.telemetry_gate.heartbeat_sent(t_send)
        self.pub.send(
            Heartbeat(
                seq=self._hb_seq,
                t_send_ns=t_send,
                node="operator",
                state=self.link_state,
                echo_t_send_ns=echo_send,
                echo_t_recv_ns=echo_recv,
                session=self._session,
                echo_session=self._robot_session,
            )
        )

    def _drain_wake_pipe(self) -> None:
        with contextlib.suppress(BlockingIOError, OSError):
            os.read(self._wake_r, 4096)

    def flush_commands(self, now: int) -> None:
        """Send what ``send_command`` queued; resend a gripper command nobody confirmed.

        A jog goes out only while the robot's telemetry is fresh (``sees_robot``):
        with it stale we cannot see what we steer, whichever half of the link
        failed, so the jog is dropped and the robot's deadman stops the arm.
        Stops, gripper and lease commands always go.

        A gripper command is one-shot: lost, or refused as stale after a stall
        on the link, the gripper would silently not move. The robot's heartbeat
        names the newest gripper command it acted on (``gripper_command_seq``,
        ``gripper_command_session``); until it names ours, it is sent again as
        a new command (fresh seq and send time) every ``gripper_confirm_ms``,
        ``gripper_resends`` times at most.
        """
        while True:
            try:
                issued, cmd = self._commands.get_nowait()
            except queue.Empty:
                break
            if isinstance(cmd, VideoSignal):  # sent below, in order, once the robot hears us
                self._held_signals.append((now, cmd))
                continue
            if cmd.action in ("arm_jog", "arm_assist"):  # the assist is held like a jog
                if (now - issued) / 1e6 > self.config.link.jog_max_age_ms:
                    # the hand may have let go since: the robot's deadman stops the arm
                    self.counters["jogs_dropped_late"] += 1
                    self._late_log(f"{cmd.action}, {(now - issued) / 1e6:.0f} ms old")
                    continue
                if not self.sees_robot(now):
                    self.counters["jogs_held_blind"] += 1
                    self._blind_log(cmd.action)
                    continue
            self._send_command(cmd, now, resends=0)
        self._release_held_signals(now)
        pending = self._gripper_pending
        if pending is None or now < pending.deadline_ns:
            return
        link = self.config.link
        if pending.resends >= link.gripper_resends:
            self._gripper_pending = None
            self.counters["gripper_unconfirmed"] += 1
            log.warning(
                "the robot never confirmed %s (%d resends): not the lease holder, or the link "
                "is down",
                pending.action,
                pending.resends,
            )
            return
        self.counters["gripper_resent"] += 1
        again = Command(seq=0, t_send_ns=0, action=pending.action, grip_level=pending.grip_level)
        self._send_command(again, now, resends=pending.resends + 1)

    def _release_held_signals(self, now: int) -> None:
        """Send the held video signals, in order, once the robot is known to hear us.

        An offer is sent once and answered once: one the link drops (the
        command link's subscription not yet through, a robot still starting)
        leaves the page waiting for its answer timeout. The robot echoing our
        heartbeat (the clock has a sample) shows the command link carries; a
        robot that never echoes gets the signals after ``VIDEO_HOLD_NS``.
        """
        held = self._held_signals
        if not held:
            return
        if not self.clock.is_synced:
            if now - held[0][0] < VIDEO_HOLD_NS:
                return
            log.warning("video signals sent unconfirmed: the robot has not echoed a heartbeat")
        while held:
            self._send_video_signal(held.popleft()[1])

    def _send_video_signal(self, cmd: VideoSignal) -> None:
        self._vsig_seq += 1
        cmd.seq, cmd.t_send_ns = self._vsig_seq, self.now()
        cmd.session, cmd.echo_session = self._session, self._robot_session
        self.pub.send(cmd)
        self.counters[f"video_{cmd.kind}s_sent"] += 1

    def _send_command(self, cmd: Command, now: int, resends: int) -> None:
        self._cmd_seq += 1
        cmd.seq, cmd.t_send_ns, cmd.session = self._cmd_seq, self.now(), self._session
        cmd.echo_session = self._robot_session
        data = self.pub.send(cmd)
        self.counters["commands_sent"] += 1
        if self._recording:
            self.recorder.write("operator/command", cmd.t_send_ns, {"seq": cmd.seq, "wire": data})
        if cmd.action.startswith("gripper"):
            deadline = now + round(self.config.link.gripper_confirm_ms * 1e6)
            self._gripper_pending = _PendingGripper(
                cmd.action, cmd.grip_level, cmd.seq, deadline, resends
            )

    def _confirm_gripper(self, stats: dict[str, float]) -> None:
        """The robot's heartbeat names the newest gripper command it acted on."""
        pending = self._gripper_pending
        if pending is None:
            return
        if stats.get("gripper_command_session") != float(self._session & SESSION_LOW_MASK):
            return
        if stats.get("gripper_command_seq", -1.0) >= pending.seq:
            self._gripper_pending = None
            self.counters["gripper_confirmed"] += 1

    # ------------------------------------------------------------ report
    def stats(self) -> dict[str, float]:
        out: dict[str, float] = {k: float(v) for k, v in self.counters.items()}
        out.update(self._latency_summary())
        for key, value in self.link.snapshot(self.now()).as_dict().items():
            if isinstance(value, (int, float)) and key != "window_s":
                out[f"link_{key}"] = float(value)
        out.update(link_health(self.sub, self.pub))  # each link up, and reopened after a give-up
        if self.signer is not None:
            out["lease_holder"] = float(self.is_controller)
        return out

    def _latency_summary(self) -> dict[str, float]:
        """Percentiles over the window, recomputed only when a sample was added."""
        n = self.counters["latency_samples"]
        if self._latency_cache[0] != n and self.latencies_ms:
            lat = np.fromiter(self.latencies_ms, dtype=np.float64)
            p50, p99 = np.percentile(lat, (50, 99))
            self._latency_cache = (
                n,
                {
                    "latency_p50_ms": float(p50),
                    "latency_p99_ms": float(p99),
                    "latency_max_ms": float(lat.max()),
                    "latency_last_ms": float(lat[-1]),
                },
            )
        return self._latency_cache[1]

    def snapshot(self) -> Snapshot:
        with self._lock:
            stim, frame = self._stim, self._frame
        now = self.now()
        _, age = self.fresh_stimulus(now)
        written = np.array(
            self._written if self._written is not None else self.renderer.retract_goals, np.int64
        )
        return Snapshot(
            link_state=self.link_state,
            stimulus=None if stim is None else stim.stimulus.copy(),
            pattern=None if stim is None else stim.pattern,
            confidence=None if stim is None else stim.confidence,
            grip_level=None if stim is None else stim.grip_level,
            frame=None if frame is None else frame.frame.copy(),
            goal_counts=written,
            goal_angles=self.calibration.counts_to_angles(written),
            age_ms=age,
            stats=self.stats(),
            robot_stats=dict(self._robot_stats),
            control=self.control_view(),
        )

    def control_view(self) -> dict[str, Any] | None:
        """The control lease as the robot's newest heartbeat states it (None when unsigned)."""
        if self.signer is None:
            return None
        own = self.signer.public
        holder, pending = self.lease_holder, self.lease_pending
        return {
            "ours": holder == own,
            "holder": None if holder is None else holder.hex()[:12],
            "pending": None if pending is None else pending.hex()[:12],
            "asked": pending == own,
            "key": own.hex()[:12],
        }


def build_operator_node(
    config: OperatorConfig, ctx: zmq.Context | None = None, recorder: Recorder | None = None
) -> OperatorNode:
    from operator_side.servos import KINDS

    servos = build_device(KINDS, config.servos, "operator.servos")
    return OperatorNode(config, servos, ctx=ctx, recorder=recorder)
