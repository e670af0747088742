"""The operator node: stimuli in, LinkGlide servo goals out; commands back to the robot.

Event-driven on the socket, paced by a 60 Hz deadline: a new stimulus is
rendered as soon as it arrives (at most one servo write per half cycle), and
the rate limiter keeps stepping toward the target on every cycle in between.
The node assembles its parts and runs the loop; each part is one concern:
``link_setup`` (keys, sockets), ``arrivals`` (what the robot sends, believed
or dropped), ``lease_view``, ``palm`` (renderer, servos, latency), ``outbox``
(commands), ``heartbeat`` and ``operator_channels`` (what it records).
"""

from __future__ import annotations

import logging
import threading
from collections import Counter, deque
from collections.abc import Callable
from typing import Any

import zmq

from common.clocks.clock import Clock, Periodic, now_ns
from common.clocks.clock_sync import ClockSync
from common.clocks.late_wake import LateWakes
from common.keys.curve import check_endpoint
from common.recording.channels import Recorder
from common.wire.messages import Command, Stimulus, VideoSignal, new_run
from common.wire.transport import Link, Receiver, Sender, link_health, make_context
from operator_side.dashboard.snapshot import Snapshot
from operator_side.node.arrivals import Arrivals, RobotHeard
from operator_side.node.config import OperatorConfig
from operator_side.node.heartbeat import HeartbeatOut
from operator_side.node.lease_view import LeaseView
from operator_side.node.link_setup import LinkKeys, Sockets, telemetry_gate_for, topics
from operator_side.node.operator_channels import OperatorChannels
from operator_side.node.outbox import Outbox
from operator_side.node.palm import Palm
from operator_side.node.snapshot import take_snapshot
from operator_side.palm.renderer import LinkGlideRenderer
from operator_side.servos.base import ServoBus
from operator_side.servos.calibration import LinkGlideCalibration

log = logging.getLogger(__name__)


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

        ``link`` is the transport (``pub``, ``sub``); ``arrivals.link_stats``, its statistics.
        """
        self.config = config
        self.servos = servos
        self.now = now
        self.recording = OperatorChannels(recorder, now)
        self.recorder = self.recording.recorder
        #: something shows raw frames (a dashboard's heatmap, a status file): only then are
        #: they subscribed to (``link.want_frames``), so a robot with no viewer skips them
        self.frames_consumed = False
        self._own_ctx = ctx is None
        self.ctx = ctx or make_context()
        self.clock = ClockSync()
        self.counters: Counter[str] = Counter()
        #: this run's boot id, on every message we send: the robot checks seq increases within it
        self.session = new_run()
        link_cfg = config.link
        keys = LinkKeys.load(link_cfg)
        self.robot_name, self.signer, self.robot_key = keys.robot_name, keys.signer, keys.robot_key
        #: with the robot's key: its signed telemetry is believed once, fresh, from its run
        self.telemetry_gate = telemetry_gate_for(keys, self.clock, link_cfg)
        self._handed_link = link is not None
        self.sockets = Sockets(link, link_cfg, keys, counters=self.counters, now=now)
        own_key = None if self.signer is None else self.signer.public
        self.lease = LeaseView(link_cfg, own_key, self.counters)
        self.heard = RobotHeard(self.clock, link_cfg.jog_blind_after_ms)
        parts = {"counters": self.counters, "now": now, "recording": self.recording}
        self.outbox = Outbox(
            link_cfg, self.heard, self.clock, self._pub, session=self.session, **parts
        )
        self.arrivals = Arrivals(
            self.clock,
            self.heard,
            self.lease,
            robot_key=self.robot_key,
            gate=self.telemetry_gate,
            counters=self.counters,
            recording=self.recording,
            on_robot_stats=self.outbox.on_robot_stats,
        )
        cal = calibration or servos.calibration or LinkGlideCalibration()
        self.palm = Palm(config, servos, cal, self.arrivals, **parts)
        self.heartbeat = HeartbeatOut(
            self.clock,
            self.heard,
            self.telemetry_gate,
            self._pub,
            session=self.session,
            now=now,
            recording=self.recording,
        )

    def _pub(self) -> Sender:
        return self.sockets.pub

    # ------------------------------------------------- parts others read
    pub = property(_pub, lambda self, pub: setattr(self.sockets, "pub", pub))

    @property
    def sub(self) -> Receiver | None:
        return self.sockets.sub

    @property
    def video_signal_handler(self) -> Callable[[VideoSignal], None] | None:
        """Called on the node's thread with each video signal the robot sends (set before run)."""
        return self.arrivals.video_signal_handler

    @video_signal_handler.setter
    def video_signal_handler(self, handler: Callable[[VideoSignal], None] | None) -> None:
        self.arrivals.video_signal_handler = handler

    @property
    def calibration(self) -> LinkGlideCalibration:
        return self.palm.calibration

    @property
    def renderer(self) -> LinkGlideRenderer:
        return self.palm.renderer

    @property
    def link_state(self) -> str:
        return self.palm.link_state

    @property
    def link_changes(self) -> deque[tuple[int, str]]:
        """(monotonic ns, new state) of the latest link state changes."""
        return self.palm.link_changes

    @property
    def latencies_ms(self) -> deque[float]:
        return self.palm.latencies_ms

    @property
    def written_goals(self) -> list[int] | None:
        """The goal counts last written to the servos (None before the first write)."""
        return self.palm.written

    @property
    def last_stimulus(self) -> Stimulus | None:
        """The newest stimulus received, fresh or not."""
        return self.arrivals.stimulus

    @property
    def lease_holder(self) -> bytes | None:
        return self.lease.holder

    @property
    def lease_pending(self) -> bytes | None:
        return self.lease.pending

    @property
    def holds_lease(self) -> bool:
        """Whether the robot's newest heartbeat names our key as the lease holder."""
        return self.lease.ours

    @property
    def loop_turns(self) -> int:
        """Turns of the loop so far (at least one per heartbeat period, robot or not):
        systemd's watchdog is pinged only while this grows (``common.process.sd_notify``), so
        a frozen or stuck loop is ended and the palm lifted by the unit's ExecStopPost."""
        return self.counters["wakeups"]

    # ---------------------------------------------- any thread: commands
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
        its turn comes is dropped (outbox.py).
        """
        cmd = Command(
            seq=0,
            t_send_ns=0,
            action=action,
            grip_level=grip_level,
            velocity=velocity,
            grantee=grantee,
        )
        self.outbox.put_command(cmd, age_ms)

    def send_video_signal(self, kind: str, viewer: int, sdp: str | None = None) -> None:
        """Queue a WebRTC offer or bye for the robot's video server; thread-safe.

        It travels the command link (signed, through the router when there is
        one), so video needs no connection of its own to the robot PC.
        """
        signal = VideoSignal(seq=0, t_send_ns=0, kind=kind, viewer=viewer, sdp=sdp)
        self.outbox.put_video_signal(signal)

    def mark_episode(self, kind: str, task: str | None = None, source: str = "dashboard") -> bool:
        """Record the operator's mark (failed, discard or success) on the episode in progress;
        thread-safe. Nothing goes to the robot. False when not recording: it would be lost."""
        return self.recording.mark(kind, task, source)

    # --------------------------------------------------------------- run
    def run(self, stop: threading.Event, duration_s: float | None = None) -> None:
        if self._handed_link:
            raise RuntimeError("a node handed a link is driven by its caller; run() opens its own")
        link_cfg = self.config.link
        if not self.servos.is_connected:
            self.servos.connect()
        bus_calibration = self.servos.calibration
        if bus_calibration is not None and bus_calibration is not self.palm.calibration:
            self.palm.use_calibration(bus_calibration)  # the bus's limits are the ones enforced
        try:
            if link_cfg.mode == "direct":
                for endpoint in (link_cfg.telemetry_endpoint, link_cfg.command_endpoint):
                    check_endpoint(endpoint, link_cfg.security)
            self.sockets.open(self.ctx, self._topics(), self.outbox.wake_r)
            self.servos.set_torque(True)
            self.palm.write(self.palm.renderer.retract_goals)
            log.info("operator node up: %s", self.sockets.describe())
            self._loop(stop, duration_s)
        finally:
            try:
                if self.servos.is_connected:
                    self.palm.lift_off_now()
            finally:
                self.sockets.close()
                self.servos.disconnect()
                if self._own_ctx:
                    self.ctx.term()

    def _topics(self) -> tuple[bytes, ...]:
        video = self.video_signal_handler is not None
        frames = self.config.link.want_frames and self.frames_consumed
        return topics(self.robot_name, frames, video)

    def _loop(self, stop: threading.Event, duration_s: float | None) -> None:
        link_cfg, palm, outbox = self.config.link, self.palm, self.outbox
        period = round(1e9 / self.config.renderer.palm_step_rate_hz)
        heartbeat = Periodic(link_cfg.heartbeat_rate_hz, link_cfg.heartbeat_early_ms / 1e3)
        next_step = self.now()
        late = _late_wakes(self.counters, link_cfg.stale_after_ms)
        t_end = None if duration_s is None else self.now() + round(duration_s * 1e9)
        while not stop.is_set() and (t_end is None or self.now() < t_end):
            due = min(next_step, heartbeat.deadline_ns)
            ready = self.sub.ready((due - self.now()) / 1e9)
            self.counters["wakeups"] += 1
            late.note(due, woke := self.now())
            changed = self.receive() if self.sub.sock in ready else False
            now = self.now()
            if changed or now >= next_step:
                # Rendered as soon as something changed; otherwise the loop sleeps
                # until the goal moves, the data would go stale, or a heartbeat.
                self.palm_step(now, period)
                next_step = palm.next_step_ns(now, period)
            if heartbeat.due(now):
                if self.lease.heartbeat_wanted():
                    self._send_heartbeat()
                heartbeat.done(now)
            self.lease.request_if_free(now, self.send_command)
            if outbox.wake_r in ready:
                outbox.drain_wake_pipe()
            self.flush_commands(now)
            self.sockets.reopen_if_silent(now, self.ctx, self._topics(), outbox.wake_r)
            # held up mid-turn (frozen or starved outside its wait): the palm was as stuck
            late.note(woke, self.now())

    # ------------------------------------------- the loop's steps, driven
    def receive(self) -> bool:
        """Drain the socket; True when a new stimulus arrived."""
        new, last_rx = self.arrivals.receive(self.sub, relinking=self.palm.link_state != "ok")
        if last_rx:
            self.sockets.last_rx_ns = last_rx
        self.counters["decode_errors"] = self.sockets.decode_errors
        return new

    def palm_step(self, now: int, period_ns: int) -> None:
        self.palm.palm_step(now, period_ns)

    def sees_robot(self, now: int) -> bool:
        """Whether the robot's telemetry is fresh enough to steer by (``jog_blind_after_ms``)."""
        return self.heard.sees_robot(now)

    def flush_commands(self, now: int) -> None:
        """Send what ``send_command`` queued; resend a gripper command nobody confirmed."""
        self.outbox.flush(now)

    def rewrite_next(self) -> None:
        """Write the next palm step's goals even if unchanged (benchmarks force each one)."""
        self.palm.written = None

    def _send_heartbeat(self) -> None:
        self.heartbeat.send(self.palm.link_state, self.stats)

    # ------------------------------------------------------------ report
    def stats(self) -> dict[str, float]:
        out: dict[str, float] = {k: float(v) for k, v in self.counters.items()}
        out.update(self.palm.latency_summary())
        for key, value in self.arrivals.link_stats.snapshot(self.now()).as_dict().items():
            if isinstance(value, (int, float)) and key != "window_s":
                out[f"link_{key}"] = float(value)
        out.update(link_health(self.sub, self.pub))  # each link up, and reopened after a give-up
        if self.signer is not None:
            out["lease_holder"] = float(self.holds_lease)
        return out

    def snapshot(self) -> Snapshot:
        """What the live views show, from any thread."""
        now, control = self.now(), self.control_view()
        return take_snapshot(self.arrivals, self.palm, now, self.stats(), control)

    def control_view(self) -> dict[str, Any] | None:
        """The control lease as the robot's newest heartbeat states it (None when unsigned)."""
        return self.lease.view()


def _late_wakes(counters: Counter[str], stale_after_ms: float) -> LateWakes:
    """The loop's late wakes: while it was starved, the palm could not lift."""
    meanwhile = f"the palm could not lift meanwhile; its staleness limit is {stale_after_ms:.0f} ms"
    return LateWakes(counters, log, "the operator's loop", meanwhile)
