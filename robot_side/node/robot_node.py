"""The robot node: frames in, stimuli out; operator messages in, device calls out.

Event-driven on frame arrival, so a stimulus leaves within microseconds of
the frame it was rendered from. Each loop turn reads as receive -> step ->
write: the operator's messages (command_desk.py), the deadman (deadman.py),
the frame through the frame rule (frame_pipeline.py), then heartbeats and
video signalling (telemetry.py, video_desk.py). Device calls run on the
devices' workers (workers.py); the loop never waits on a device.
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
from collections import Counter

import zmq

from common.clocks.clock import Clock, Periodic, now_ns
from common.clocks.clock_sync import ClockSync
from common.keys.curve import Authenticator
from common.recording.channels import NullRecorder, Recorder
from common.wire.messages import Stimulus, VideoSignal, new_run
from common.wire.transport import Link, Receiver, Sender, link_health, make_context
from robot_side.arm.base import Arm
from robot_side.gripper.base import Gripper
from robot_side.node.assist import Assist
from robot_side.node.command_desk import CommandDesk
from robot_side.node.commands.stop_latch import StopLatch
from robot_side.node.config import RobotConfig
from robot_side.node.deadman import NEVER_NS, Deadman
from robot_side.node.frame_pipeline import FramePipeline
from robot_side.node.frame_rule import Classifier
from robot_side.node.handover import Handover
from robot_side.node.link_setup import open_link, stream_signer, wire_name
from robot_side.node.loop_watch import LoopWatch
from robot_side.node.telemetry import (
    HeartbeatSchedule,
    Telemetry,
    frame_display_rate_hz,
    node_stats,
    stats_period_ms,
)
from robot_side.node.video_desk import VideoDesk, video_signalling
from robot_side.node.workers import DeviceWorkers
from robot_side.tactile.base import TactileSample, TactileSensor

log = logging.getLogger(__name__)


class RobotNode:
    """Devices and classifier are passed in, so tests and simulators can supply them."""

    def __init__(
        self,
        config: RobotConfig,
        tactile: TactileSensor | None,
        *,
        classifier: Classifier | None = None,
        gripper: Gripper | None = None,
        arm: Arm | None = None,
        ctx: zmq.Context | None = None,
        recorder: Recorder | None = None,
        now: Clock = now_ns,
        link: Link | None = None,
    ) -> None:
        """``now`` and ``link``: the clock and the link, handed in to replay or bench the node.

        A node handed a link is driven through ``process`` and ``receive`` and needs no
        ``tactile``.
        """
        if config.render.mode == "mask" and classifier is None:
            raise ValueError("mask mode needs a classifier")
        self.config = config
        self.tactile = tactile
        self.gripper = gripper
        self.arm = arm
        self.recorder = recorder or NullRecorder()
        recording = None if isinstance(self.recorder, NullRecorder) else self.recorder
        self._recording = recording is not None
        self._own_ctx = ctx is None
        self.ctx = ctx or make_context()
        self.now = now
        self.counters: Counter[str] = Counter()
        #: this run's boot id, on everything we send: seqs restart with it, so an operator
        #: tells a restart from a replay and refuses what an older run sent (replay_window.py)
        self.session = new_run()
        link_cfg = config.link
        #: our name on the wire (b"" = unnamed); ConfigError for a name the protocol forbids
        self.name = wire_name(link_cfg.robot_name)
        self.workers = DeviceWorkers(arm, gripper, link_cfg.heartbeat_rate_hz)
        self.pipeline = FramePipeline(
            config,
            classifier,
            self._send,
            now=now,
            session=self.session,
            counters=self.counters,
            recorder=recording,
            grip_level=lambda: self.workers.grip_level,
        )
        #: the stop latch, the device workers' queue and the robot/command recording
        self.handover = handover = Handover(
            self.workers, counters=self.counters, now=now, recorder=recording
        )
        #: the robot-side reflex the holder's arm_assist enables (off until held)
        self.assist = Assist(
            config.assist,
            self.pipeline,
            self.workers,
            act=handover.act_for_holder,
            stop_latched=lambda: handover.stop_latch.latched,
            grip_level=lambda: handover.grip_level_commanded,
            limits=None if arm is None else arm.limits,
            now=now,
            recorder=recording,
            announce=self._announce,
        )
        self.desk = CommandDesk(
            link_cfg,
            handover,
            self.assist,
            counters=self.counters,
            now=now,
            on_video=self._on_video,
            announce=self._announce,
            session=self.session,
        )
        #: signs everything we send when set: operators holding our key drop what is not ours
        self.signer = stream_signer(link_cfg)
        self.video = VideoDesk(
            video_signalling(link_cfg),
            link_cfg.video_viewer_timeout_s,
            counters=self.counters,
            now=now,
            session=self.session,
            last_heard_ns=self.desk.peers.last_heard_ns,
            who=self.desk.peers.entry,
            offers_per_s=link_cfg.video_offers_per_s,
        )
        self.deadman = Deadman(link_cfg.deadman_ms, self.counters)
        self.telemetry = Telemetry(
            self.desk,
            name=self.name,
            session=self.session,
            now=now,
            stats=self.stats,
            counters=self.counters,
            stats_period_ms=stats_period_ms(link_cfg),
        )
        #: set it (SIGHUP: ``systemctl reload``) to read the roster again at the next loop turn
        self.roster_reload = threading.Event()
        #: commands are not read again before this (monotonic ns) after a full batch
        self._commands_paused_until = 0
        self._handed_link = link is not None
        self.pub: Sender | None = None
        self.sub: Receiver | None = None
        self._frames_poller: zmq.Poller | None = None
        self._auth: Authenticator | None = None
        if link is not None:
            self._attach(link.pub, link.sub)

    def _attach(self, pub: Sender | None, sub: Receiver | None) -> None:
        self.pub, self.sub = pub, sub
        self.video.pub = self.telemetry.pub = pub

    # ---------------------------------------------------------- what others read
    def endpoints(self) -> dict[str, str]:
        """Where the link's ends are (its bound ports, on a direct link): the node's READY=1
        says them, so a node configured with port 0 tells its peer where it listens."""
        return {
            name: end.endpoint
            for name, end in (("telemetry", self.pub), ("commands", self.sub))
            if getattr(end, "endpoint", "")
        }

    @property
    def link_state(self) -> str:
        return self.deadman.link_state

    @property
    def clock(self) -> ClockSync:
        """The clock offset to the operator of an unsigned link (each roster key has its own)."""
        return self.desk.clock

    @property
    def stop_latch(self) -> StopLatch:
        return self.handover.stop_latch

    @property
    def uses_compiled_step(self) -> bool:
        """Whether frames take the one compiled call (compiled_step.py), not the plain path."""
        return self.pipeline.renderer.compiled is not None

    @property
    def last_stimulus(self) -> Stimulus | None:
        """The stimulus the operator renders now: the last one sent, keyframes included."""
        return self.pipeline.last_stimulus

    def resend_next(self) -> None:
        """Render and send the next frame whatever was sent before (benchmarks force each one)."""
        self.pipeline.resend_next()

    def process(self, sample: TactileSample) -> Stimulus | None:
        """One frame through the frame rule without the rate cap (``pipeline.offer`` has it)."""
        return self.pipeline.process(sample)

    # ------------------------------------------------------------------- run
    def run(self, stop: threading.Event, duration_s: float | None = None) -> None:
        """Connect, loop until ``stop`` is set (or ``duration_s``), and always stop the arm."""
        if self._handed_link:
            raise RuntimeError("a node handed a link is driven by its caller; run() opens its own")
        link_cfg = self.config.link
        with contextlib.ExitStack() as stack:
            for device in (self.tactile, self.gripper, self.arm):
                if device is not None and not device.is_connected:
                    device.connect()
                    stack.callback(device.disconnect)
            self.workers.start(stack)
            signalling = self.video.signalling
            pub, sub, self._auth = open_link(
                stack,
                self.ctx,
                link_cfg,
                name=self.name,
                signer=self.signer,
                serves_video=signalling is not None,
            )
            self._attach(pub, sub)
            # one wait for both: a frame the loop asked for, or a word from the operator
            sub.poller.register(self.tactile.frame_fd(), zmq.POLLIN)
            # and one for frames alone, while a command backlog waits its turn
            self._frames_poller = zmq.Poller()
            self._frames_poller.register(self.tactile.frame_fd(), zmq.POLLIN)
            if signalling is not None:
                stack.callback(signalling.close)
            log.info("robot node up: telemetry %s, commands %s", pub.endpoint, sub.endpoint)
            self._loop(stop, duration_s)
        if self._own_ctx:
            self.ctx.term()

    def _loop(self, stop: threading.Event, duration_s: float | None) -> None:
        heartbeat = HeartbeatSchedule.of_link(self.config.link)
        frame_msgs = display_frame_grid(self.config)
        pipeline, watch = self.pipeline, LoopWatch(self.counters)
        t_end = None if duration_s is None else self.now() + round(duration_s * 1e9)
        while not stop.is_set() and (t_end is None or self.now() < t_end):
            # Sleep through the frames the rate cap would drop (120 Hz in, 60 out). An operator's
            # message wakes the loop at once (stamped on arrival); the heartbeat and the deadman
            # at their deadlines, which a wake much later than (``watch``) says was starved.
            wanted_after = pipeline.last_seq + pipeline.frames_until_due(self.now())
            sample = self.tactile.take_newer(wanted_after)
            due = self.now()
            if sample is None:
                beat = heartbeat.wake_ns(self.telemetry.now_wanted)
                due = min(beat, self._deadman_deadline(), t_end or NEVER_NS)
                self._wait(due)
                sample = self.tactile.take_newer(wanted_after)
            self.counters["wakeups"] += 1
            now = self.now()
            watch.woke(due, now)
            # receive
            if self.roster_reload.is_set():
                self.roster_reload.clear()
                self.desk.reload_roster(now)
            if now >= self._commands_paused_until:
                self.receive(now)
            self.check_deadman(now)
            self.pub.read_subscriptions()
            watch.mark("receive")
            # step: the frame, through the frame rule (the rate cap included)
            if sample is not None:
                pipeline.offer(sample, self.now())
                if frame_msgs is not None and frame_msgs.due(now):
                    self.telemetry.send_frame(sample)
                    frame_msgs.done(now)
            watch.mark("frame")
            # the assist acts on the pattern just recognised, locally, with no round trip
            self.assist.step(self.now())
            # write: heartbeats and video answers
            on_grid = heartbeat.due(now)  # else an announcement: one more, off the grid
            if on_grid or (self.telemetry.now_wanted and heartbeat.may_announce(now)):
                self._send_heartbeat()
                heartbeat.sent(now, on_grid)
            watch.mark("assist and heartbeat")
            self.video.serve(now)
            watch.turn_done("video")

    def _wait(self, deadline: int) -> None:
        """Until a frame, an operator message or ``deadline``; frames only during a backlog."""
        paused_until = self._commands_paused_until
        if self.now() < paused_until:  # a backlog: frames only until its next turn
            wait_ms = math.ceil(max(0, min(deadline, paused_until) - self.now()) / 1e6)
            self._frames_poller.poll(wait_ms)
        else:
            self.sub.ready((deadline - self.now()) / 1e9)

    # --------------------------------------------------------------- receive
    def receive(self, now: int) -> None:
        """Read at most one batch of operator messages and act on it (command_desk.py).

        A full batch means a backlog: the socket is left alone for
        ``command_backlog_pause_ms`` so that frames, not a flood of commands,
        get the loop. What waits meanwhile only ages, and stale commands are
        refused (command_gate.py), so the pause can never move the arm late.
        """
        link_cfg = self.config.link
        batch = self.sub.drain(link_cfg.max_messages_per_wake)
        if len(batch) >= link_cfg.max_messages_per_wake:
            self._commands_paused_until = now + round(link_cfg.command_backlog_pause_ms * 1e6)
            self.counters["command_backlog_pauses"] += 1
        self.desk.take(batch, now)
        self.counters["decode_errors"] = self.sub.rejected_total

    def _on_video(self, msg: VideoSignal, signer: bytes | None) -> None:
        self.video.on_signal(msg, signer)

    def _announce(self) -> None:
        self.telemetry.announce()

    def _deadman_deadline(self) -> int:
        return self.deadman.deadline_ns(self.desk.gate)

    def check_deadman(self, now: int) -> None:
        """The operator silent for ``deadman_ms``: stop the devices; the holder's lease ends."""
        if self.deadman.check(self.desk.gate, now):
            self.workers.stop_devices("operator silent")
            self.desk.holder_silent(now)

    # ----------------------------------------------------------------- write
    def _send(self, msg: Stimulus) -> bytes:
        return self.pub.send(msg)

    def _send_heartbeat(self) -> None:
        now, pipeline = self.now(), self.pipeline  # one time: the record's is replay's
        if self._recording:
            self.recorder.write("robot/link", now, {"state": self.link_state, **self.stats()})
        self.telemetry.send_heartbeat(
            self.link_state, pipeline.last_change, pipeline.last_capture_ns
        )
        pipeline.heartbeat_sent(now)

    def stats(self) -> dict[str, float]:
        """The counters, the workers', video's and CURVE's, and the devices' state."""
        out = node_stats(self.counters, self.workers, self.video.signalling, self._auth,
                         self.pipeline, self.desk)  # fmt: skip
        out.update(link_health(self.pub, self.sub))  # each end up, and reopens
        return out


def display_frame_grid(config: RobotConfig) -> Periodic | None:
    """When raw frames go out for the operator's heatmaps: on a fixed grid, so the average
    rate is the configured one even though the loop only wakes for the frames it renders (at
    60 Hz, 15 Hz is every 4th); None when they never do."""
    rate = frame_display_rate_hz(config.link)
    return Periodic(rate, 0.5 / config.publish_rate_hz) if rate > 0 else None
