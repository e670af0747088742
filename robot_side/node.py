"""The robot node: frames in, stimuli out; operator commands in, device actions out.

Event-driven on frame arrival, so a stimulus leaves within microseconds of
the frame it was rendered from; at most ``publish_rate_hz`` frames are
rendered per second. Work is skipped whenever it cannot change the output:
no inference without contact, nothing recomputed for an identical frame,
nothing resent when the stimulus did not change (heartbeats confirm it, and
a keyframe every ``keyframe_interval_ms`` bounds the damage of a lost change).
"""

from __future__ import annotations

import collections
import contextlib
import importlib.util
import logging
import math
import secrets
import threading
from collections import Counter
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np
import zmq

from common.clock import Clock, Periodic, now_ns
from common.clock_sync import ClockSync
from common.codec import MAX_STATS, DecodeError, check_robot_name, name_prefix
from common.devices import Device, build_device
from common.errors import ConfigError, DeviceError
from common.logs import BurstLog
from common.messages import (
    LEASE_ACTIONS,
    SESSION_LOW_MASK,
    Command,
    Heartbeat,
    Stimulus,
    TactileFrame,
    VideoSignal,
)
from common.recording import NullRecorder, Recorder
from common.roster import Roster, check_replacement, load_roster
from common.security import Authenticator, check_endpoint, client_options, server_options
from common.transport import Link, Publisher, Receiver, Sender, Subscriber, make_context
from robot_side.command_gate import CommandGate
from robot_side.config import RobotConfig
from robot_side.device_worker import DeviceRequest, DeviceWorker
from robot_side.lease import ControlLease
from robot_side.recovery import DeviceRecovery
from robot_side.rendering import NO_CELLS, render_frame, sanitize_frame, sanitize_with_peak
from robot_side.stop_latch import REFUSALS, StopLatch
from robot_side.tactile.base import TactileSample, TactileSensor
from robot_side.video.link_signalling import LinkSignalling

log = logging.getLogger(__name__)

#: The arm's reconnects back off to at most this: a try while the controller is still away
#: costs one refused TCP connect (URArm checks its ports before ur-rtde's constructors), so
#: a controller that reboots or gets its cable back is used again within about this long.
ARM_RECONNECT_MAX_BACKOFF_S = 2.0
#: the arm telemetry that describes the robot node's own limits, not the controller's state
ARM_ENVELOPE_KEYS = ("arm_ws_", "arm_max_")

_NO_CELLS = list(NO_CELLS)  # every linkage lifted
_NEVER_NS = 2**63 - 1  # a deadline that never comes


class Prediction(Protocol):
    pattern: int
    confidence: float
    angle_probs: tuple[float, ...]
    position_probs: tuple[float, ...]


class Classifier(Protocol):
    """What the node needs of robot_side.perception.TiltClassifier (no import of it here)."""

    def predict_one(self, frame: np.ndarray) -> Prediction: ...


class RobotNode:
    """Devices and classifier are passed in, so tests and simulators can supply them."""

    def __init__(
        self,
        config: RobotConfig,
        tactile: TactileSensor | None,
        *,
        classifier: Classifier | None = None,
        gripper: Any | None = None,
        arm: Any | None = None,
        ctx: zmq.Context | None = None,
        recorder: Recorder | None = None,
        now: Clock = now_ns,
        link: Link | None = None,
    ) -> None:
        """``now`` and ``link``: the clock and the link, handed in to replay or bench the node.

        A node handed a link is driven through ``process`` and needs no ``tactile``.
        """
        if config.render.mode == "mask" and classifier is None:
            raise ValueError("mask mode needs a classifier")
        self.config = config
        self.tactile = tactile
        self.classifier = classifier
        # mask mode on the numba classifier: one compiled call per frame (None otherwise)
        self._compiled = compiled_step_for(classifier, config.render)
        self.gripper = gripper
        self.arm = arm
        self.recorder = recorder or NullRecorder()
        self._recording = not isinstance(self.recorder, NullRecorder)
        self._own_ctx = ctx is None
        self.ctx = ctx or make_context()
        self.counters: Counter[str] = Counter()
        self.link_state = "down"
        #: (monotonic ns, new state) of the latest link state changes
        self.link_changes: collections.deque[tuple[int, str]] = collections.deque(maxlen=256)
        #: this run's boot id, on everything we send: seqs restart with it, so an operator
        #: tells a restart from a replay and refuses what an older run sent (replay_window.py)
        self.session = secrets.randbits(63) or 1
        self._stim_seq = 0
        self._hb_seq = 0
        self._frame_msg_seq = 0
        self._last_frame: np.ndarray | None = None
        self._last_cells: list[float] | None = None  # the last stimulus sent, row by row
        self._last_pattern: int | None = None
        self._last_stim_msg: Stimulus | None = None
        self._last_publish_ns = 0
        self._last_process_ns = 0
        self._last_capture_ns: int | None = None
        self.clock = ClockSync()
        #: what the robot acts on, judged on the operator's clock (command_gate.py)
        self.gate = CommandGate(self.clock, round(config.link.max_command_age_ms * 1e6))
        #: our name on the wire (b"" = unnamed); ConfigError for a name the protocol forbids
        self.name = _wire_name(config.link.robot_name)
        #: with a roster: signed commands, obeyed only from the lease holder (lease.py)
        self.lease: ControlLease | None = None
        #: an operator's arm_stop holds the arm until the holder's arm_resume (stop_latch.py)
        self.stop_latch = StopLatch()
        #: set it (SIGHUP: ``systemctl reload``) to read the roster again at the next loop turn
        self.roster_reload = threading.Event()
        #: the roster in force (a reload that would lock everyone out keeps it)
        self.roster: Roster | None = None
        if config.link.roster_file is not None:
            roster = self.roster = load_roster(config.link.roster_file)
            self.lease = ControlLease(
                roster.by_signing_key(),
                round(config.link.max_command_age_ms * 1e6),
                round(config.link.lease_request_timeout_ms * 1e6),
            )
            self.gate = self.lease.holder_gate
        elif config.link.mode == "relay":
            raise ConfigError(
                "robot link.mode = 'relay' needs link.roster_file: through a relay only "
                "signed commands from the lease holder may move the arm (docs/security.md)"
            )
        #: signs everything we send when set: operators holding our key drop what is not ours
        self.signer = None
        link_cfg = config.link
        if link_cfg.mode == "relay" and link_cfg.signing_key_file is None:
            if not link_cfg.unsigned_stream:
                raise ConfigError(
                    "robot link.mode = 'relay' signs its stream: set link.signing_key_file "
                    "(`deepxpalm keys robot --name NAME` makes it), or link.unsigned_stream = "
                    "true to let a compromised relay forge what palms feel (docs/security.md)"
                )
            log.warning("link.unsigned_stream: this robot's stream is not signed")
        if config.link.signing_key_file is not None:
            from common.signing import load_signer  # cryptography only when signing

            self.signer = load_signer(config.link.signing_key_file)
        #: viewers' WebRTC signalling, carried to the local video server (None: no video here)
        self.video: LinkSignalling | None = None
        if config.link.video_url:
            if importlib.util.find_spec("websockets") is None:
                raise ConfigError(
                    "robot link.video_url is set but websockets is not installed: "
                    "pip install 'deepxpalm[video]' on the robot PC"
                )
            self.video = LinkSignalling(
                config.link.video_url, token_file=config.link.video_token_file
            )
        self._video_heard_ns: int = 0  # direct link: when the operator was last heard
        self._next_video_expiry_ns = 0
        self._vsig_seq = 0
        self._lease_changes_seen = 0
        self._echo_turn = 0  # round robin over the operators whose heartbeats we echo
        self._heartbeat_now = False  # a lease change is announced at once, not in 50 ms
        self._grip_level: int | None = None  # the gripper worker's latest reading
        #: (seq, low 32 bits of the session) of the newest gripper command handed to the gripper
        self._gripper_ack: tuple[float, float] | None = None
        self._arm_state: dict[str, float] = {}  # the arm worker's latest reading
        self._first_seq: int | None = None
        self._last_seq = 0
        self._last_capture_seen: tuple[int, int] | None = None
        self._frame_period_ns = 0.0  # estimated from the frames' capture times
        self._skip_requested = 0
        never = threading.Event()  # replaced in run(); lets stats() work before it
        self._arm_recovery = DeviceRecovery(arm, "arm", never)
        self._gripper_recovery = DeviceRecovery(gripper, "gripper", never)
        #: device calls run on these, never on the frame loop (None before run())
        self._workers: dict[str, DeviceWorker] = {}
        #: commands are not read again before this (monotonic ns) after a full batch
        self._commands_paused_until = 0
        self.now = now
        self._handed_link = link is not None
        self.pub: Sender | None = link.pub if link is not None else None
        self.sub: Receiver | None = link.sub if link is not None else None
        self._frames_poller: zmq.Poller | None = None
        self._auth: Authenticator | None = None
        self._stats_cut = BurstLog(log, "heartbeat stats over the protocol's limit")

    # ------------------------------------------------------------------ run
    def run(self, stop: threading.Event, duration_s: float | None = None) -> None:
        """Connect, loop until ``stop`` is set (or ``duration_s``), and always stop the arm."""
        if self._handed_link:
            raise RuntimeError("a node handed a link is driven by its caller; run() opens its own")
        link = self.config.link
        with contextlib.ExitStack() as stack:
            for device in (self.tactile, self.gripper, self.arm):
                if device is not None and not device.is_connected:
                    device.connect()
                    stack.callback(device.disconnect)
            halt = threading.Event()  # ends device recoveries before the devices close
            self._arm_recovery = DeviceRecovery(
                self.arm, "arm", halt, max_backoff_s=ARM_RECONNECT_MAX_BACKOFF_S
            )
            self._gripper_recovery = DeviceRecovery(self.gripper, "gripper", halt)
            stack.callback(self._arm_recovery.join)
            stack.callback(self._gripper_recovery.join)
            stack.callback(halt.set)
            self._start_workers(stack)
            for endpoint in (link.telemetry_endpoint, link.command_endpoint):
                check_endpoint(endpoint, link.security)
            bind = link.mode == "bind"
            if bind:
                auth = self._auth = Authenticator(self.ctx, link.security)
                stack.callback(auth.stop)
                opts = server_options(link.security)
            else:  # the relay is the CURVE server; its allowlist and ours (the roster) both apply
                opts = client_options(link.security)
            name = self.name
            self.pub = Publisher(
                self.ctx,
                link.telemetry_endpoint,
                bind=bind,
                sock_opts=opts,
                name=name,
                signer=self.signer,
                watch_subscriptions=not bind,  # the relay tells us what anyone subscribed to
            )
            stack.callback(self.pub.close)
            topics: tuple[bytes, ...] = (b"",)
            if name:
                wanted = [Command.TOPIC, Heartbeat.TOPIC]
                if self.video is not None:  # viewers' offers, only where a camera is served
                    wanted.append(VideoSignal.TOPIC)
                topics = tuple(name_prefix(topic, name) for topic in wanted)
            self.sub = Subscriber(
                self.ctx,
                link.command_endpoint,
                bind=bind,
                sock_opts=opts,
                name="robot commands",
                topics=topics,
                expect_name=name,
            )
            stack.callback(self.sub.close)
            # one wait for both: a frame the loop asked for, or a word from the operator
            self.sub.poller.register(self.tactile.frame_fd(), zmq.POLLIN)
            # and one for frames alone, while a command backlog waits its turn
            self._frames_poller = zmq.Poller()
            self._frames_poller.register(self.tactile.frame_fd(), zmq.POLLIN)
            if self.gripper is not None:
                self._workers["gripper"].post(
                    DeviceRequest("gripper_activate", self.gripper.activate)
                )
            if self.video is not None:
                stack.callback(self.video.close)
            log.info(
                "robot node up: telemetry %s, commands %s", self.pub.endpoint, self.sub.endpoint
            )
            self._loop(stop, duration_s)
        if self._own_ctx:
            self.ctx.term()

    def _loop(self, stop: threading.Event, duration_s: float | None) -> None:
        link = self.config.link
        heartbeat = Periodic(link.heartbeat_rate_hz, link.heartbeat_early_ms / 1e3)
        # raw frames on a fixed grid, so the average rate is the configured one even though
        # the loop only wakes for the frames it renders (at 60 Hz, 15 Hz is every 4th)
        frame_msgs = (
            Periodic(link.frame_display_rate_hz, 0.5 / self.config.publish_rate_hz)
            if link.frame_display_rate_hz > 0
            else None
        )
        min_interval = round(0.9e9 / self.config.publish_rate_hz)
        t_end = None if duration_s is None else self.now() + round(duration_s * 1e9)
        while not stop.is_set() and (t_end is None or self.now() < t_end):
            # Sleep through the frames that will not be rendered (120 Hz in, 60 out):
            # wait for the first one due, instead of waking for each. A command or
            # heartbeat from the operator wakes the loop at once (and is stamped on
            # arrival); the heartbeat and the deadman wake it at their deadlines.
            self._skip_requested = self._frames_until_due(min_interval)
            wanted_after = self._last_seq + self._skip_requested
            sample = self.tactile.take_newer(wanted_after)
            if sample is None:
                deadline = min(
                    heartbeat.deadline_ns, self._deadman_deadline_ns(), t_end or _NEVER_NS
                )
                paused_until = self._commands_paused_until
                if self.now() < paused_until:  # a backlog: frames only until its next turn
                    wait_ms = math.ceil(max(0, min(deadline, paused_until) - self.now()) / 1e6)
                    self._frames_poller.poll(wait_ms)
                else:
                    self.sub.ready((deadline - self.now()) / 1e9)
                sample = self.tactile.take_newer(wanted_after)
            self.counters["wakeups"] += 1
            now = self.now()
            if self.roster_reload.is_set():
                self.roster_reload.clear()
                self.reload_roster(now)
            if now >= self._commands_paused_until:
                self._handle_commands(now)
            self._check_deadman(now)
            self.pub.read_subscriptions()
            if sample is not None:
                self._account(sample)
                if now - self._last_process_ns >= min_interval:
                    self.process(sample)
                else:
                    self.counters["frames_skipped_rate"] += 1
                if frame_msgs is not None and frame_msgs.due(now):
                    self._send_frame(sample)
                    frame_msgs.done(now)
            if heartbeat.due(now) or self._heartbeat_now:  # with frames, on a frame's wake-up
                self._send_heartbeat()
                heartbeat.done(now)
            if self.video is not None:
                self._serve_video(now)

    # ------------------------------------------------------------- frames
    def _frames_until_due(self, min_interval: int) -> int:
        """Frames that will arrive before the next render is due (0 before the rate is known)."""
        period = self._frame_period_ns
        if not self._last_seq or period <= 0:
            return 0
        remaining = self._last_process_ns + min_interval - self.now()
        return max(0, int(remaining // period))

    def _account(self, sample: TactileSample) -> None:
        last = self._last_capture_seen
        if last is not None and sample.seq > last[0]:
            interval = (sample.t_capture_ns - last[1]) / (sample.seq - last[0])
            if interval > 0:  # the sensor's frame period, smoothed
                p = self._frame_period_ns
                self._frame_period_ns = interval if p <= 0 else 0.9 * p + 0.1 * interval
        self._last_capture_seen = (sample.seq, sample.t_capture_ns)
        if self._first_seq is None:
            self._first_seq = sample.seq
        gap = max(0, sample.seq - self._last_seq - 1) if self._last_seq else 0
        slept = min(gap, self._skip_requested)  # frames deliberately not woken for
        self.counters["frames_skipped_rate"] += slept
        self.counters["frames_superseded"] += gap - slept
        self._last_seq = sample.seq

    def process(self, sample: TactileSample) -> Stimulus | None:
        """Render one frame and publish the stimulus if it changed. Returns what was sent."""
        now = self.now()
        self._last_process_ns = now
        if (now - sample.t_capture_ns) / 1e6 > self.config.max_frame_age_ms:
            self.counters["frames_stale"] += 1
            return None
        self.counters["frames_processed"] += 1
        self._last_capture_ns = sample.t_capture_ns
        truth = sample.truth.pattern if sample.truth is not None else None
        if self._compiled is not None:
            outcome = self._render_compiled(sample, now)
        else:
            outcome = self._render(sample, now, truth)
        if outcome is None:
            self.counters["frames_identical"] += 1
            return self._maybe_keyframe(sample)
        contact, cells, pattern, confidence = outcome
        if not self._changed(cells, pattern):
            self.counters["stimuli_unchanged"] += 1
            return self._maybe_keyframe(sample)
        return self._publish(sample, cells, contact, pattern, confidence, truth, keyframe=False)

    def _render(
        self, sample: TactileSample, now: int, truth: int | None
    ) -> tuple[bool, list[float], int | None, float | None] | None:
        """(contact, cells, pattern, confidence), or None for the last frame again."""
        render = self.config.render
        frame, peak = sanitize_with_peak(sample.frame)
        if self._recording:
            self._record_frame(sample, frame, now)
        contact = peak >= render.contact_threshold_n  # is_contact, from the same pass
        if not contact:
            self.counters["frames_no_contact"] += 1
            self._last_frame = None
            return False, _NO_CELLS, None, None
        if self._last_frame is not None and np.array_equal(frame, self._last_frame):
            return None
        self._last_frame = frame
        confidence: float | None = None

        def classify(f: np.ndarray) -> int:
            nonlocal confidence
            prediction = self.classifier.predict_one(f)
            confidence = min(max(prediction.confidence, 0.0), 1.0)
            self._count_inference(sample, prediction.angle_probs, prediction.position_probs,
                                  prediction.pattern, confidence)  # fmt: skip
            return prediction.pattern

        cells, pattern = render_frame(frame, True, render, classify=classify, truth=truth)
        if render.mode == "mask_ground_truth":
            confidence = 1.0 if truth is not None else None
        return True, cells, pattern, confidence

    def _render_compiled(
        self, sample: TactileSample, now: int
    ) -> tuple[bool, list[float], int | None, float | None] | None:
        """``_render`` in mask mode through the one compiled call (compiled_step.py)."""
        step = self._compiled
        r = step.step(sample.frame)
        if self._recording:
            self._record_frame(sample, step.sanitized.copy(), now)
        status = r[0]
        if status == step.NO_CONTACT:
            self.counters["frames_no_contact"] += 1
            return False, _NO_CELLS, None, None
        if status == step.IDENTICAL:
            return None
        angle, position = int(r[step.ANGLE]), int(r[step.POSITION])
        at = step.PROBS
        angle_probs = tuple(r[at : at + 4])
        position_probs = tuple(r[at + 4 : at + 7])
        pattern = 3 * angle + position
        confidence = min(max(angle_probs[angle] * position_probs[position], 0.0), 1.0)
        self._count_inference(sample, angle_probs, position_probs, pattern, confidence)
        return True, r[step.CELLS : step.CELLS + 9], pattern, confidence

    def _record_frame(self, sample: TactileSample, frame: np.ndarray, now: int) -> None:
        self.recorder.write(
            "robot/frame",
            now,
            {"frame": frame, "frame_seq": sample.seq, "t_capture_ns": sample.t_capture_ns},
        )

    def _count_inference(
        self,
        sample: TactileSample,
        angle_probs: tuple[float, ...],
        position_probs: tuple[float, ...],
        pattern: int,
        confidence: float,
    ) -> None:
        self.counters["inferences"] += 1
        if self._recording:
            self.recorder.write(
                "robot/prediction",
                self.now(),
                {
                    "frame_seq": sample.seq,
                    "angle_probs": np.array(angle_probs, np.float32),
                    "position_probs": np.array(position_probs, np.float32),
                    "pattern": pattern,
                    "confidence": confidence,
                },
            )

    def resend_next(self) -> None:
        """Render and send the next frame whatever was sent before (benchmarks force each one)."""
        self._last_cells = None
        self._last_frame = None
        if self._compiled is not None:
            self._compiled.forget()

    @property
    def uses_compiled_step(self) -> bool:
        """Whether frames take the one compiled call (compiled_step.py), not the plain path."""
        return self._compiled is not None

    @property
    def last_stimulus(self) -> Stimulus | None:
        """The stimulus the operator renders now: the last one sent, keyframes included."""
        return self._last_stim_msg

    def _changed(self, cells: list[float], pattern: int | None) -> bool:
        """Another set of pressed cells, or a force moved by more than the dead band."""
        last = self._last_cells
        if last is None or pattern != self._last_pattern:
            return True
        deadband = self.config.render.deadband_n
        return any(
            (new > 0) != (old > 0) or abs(new - old) > deadband
            for new, old in zip(cells, last, strict=True)
        )

    def _maybe_keyframe(self, sample: TactileSample) -> Stimulus | None:
        interval = self.config.render.keyframe_interval_ms * 1e6
        msg = self._last_stim_msg
        if msg is None or self.now() - self._last_publish_ns < interval:
            return None
        truth = sample.truth.pattern if sample.truth is not None else None
        return self._publish(
            sample, self._last_cells, msg.contact, msg.pattern, msg.confidence, truth, keyframe=True
        )

    def _publish(
        self,
        sample: TactileSample,
        cells: list[float],
        contact: bool,
        pattern: int | None,
        confidence: float | None,
        truth: int | None,
        *,
        keyframe: bool,
    ) -> Stimulus:
        self._stim_seq += 1
        now = self.now()
        msg = Stimulus(
            seq=self._stim_seq,
            t_send_ns=now,
            t_capture_ns=sample.t_capture_ns,
            frame_seq=sample.seq,
            mode=self.config.render.mode,
            contact=contact,
            stimulus=np.array(cells, np.float32).reshape(3, 3),
            pattern=pattern,
            confidence=confidence,
            grip_level=self._grip_level,
            keyframe=keyframe,
            sim_truth_pattern=truth,
            session=self.session,
        )
        data = self.pub.send(msg)
        if self._recording:
            self.recorder.write("robot/stimulus", now, {"seq": msg.seq, "wire": data})
        self._last_cells = cells
        self._last_pattern = pattern
        self._last_stim_msg = msg
        self._last_publish_ns = now
        self.counters["keyframes" if keyframe else "stimuli_published"] += 1
        return msg

    def _send_frame(self, sample: TactileSample) -> None:
        if not self.pub.wanted(name_prefix(TactileFrame.TOPIC, self.name)):
            self.counters["frames_unwanted"] += 1  # nobody subscribed: not even encoded
            return
        self._frame_msg_seq += 1
        frame = sanitize_frame(sample.frame)
        self.pub.send(
            TactileFrame(
                seq=self._frame_msg_seq,
                t_send_ns=self.now(),
                t_capture_ns=sample.t_capture_ns,
                frame_seq=sample.seq,
                frame=frame,
                session=self.session,
            )
        )

    # ----------------------------------------------------------- commands
    def _start_workers(self, stack: contextlib.ExitStack) -> None:
        """A worker per device; on shutdown each finishes with a stop (the arm) or a hold."""
        link = self.config.link
        if self.arm is not None:
            arm = self._workers["arm"] = DeviceWorker(
                "arm",
                self._arm_recovery,
                idle_poll=self._read_arm_state,
                idle_poll_s=1.0 / link.heartbeat_rate_hz,
            )
            stack.callback(arm.close, DeviceRequest("arm_stop", self.arm.stop))
        if self.gripper is not None:
            gripper = self._workers["gripper"] = DeviceWorker(
                "gripper",
                self._gripper_recovery,
                idle_poll=self._read_grip_level,
                idle_poll_s=1.0 / link.heartbeat_rate_hz,
            )
            stack.callback(gripper.close)

    def _read_arm_state(self) -> None:
        """The arm worker's poll: pose, speed and safety state for the operator's dashboard."""
        telemetry = getattr(self.arm, "telemetry", None)
        self._arm_state = telemetry() if telemetry is not None else {}

    def _read_grip_level(self) -> None:
        """The gripper worker's poll: the stimuli carry the grip level without a device call."""
        self._grip_level = self.gripper.grip_level()

    def _handle_commands(self, now: int) -> None:
        """Read at most one batch; act on the newest admitted command of each device.

        A full batch means a backlog: the socket is left alone for
        ``command_backlog_pause_ms`` so that frames, not a flood of commands,
        get the loop. What waits meanwhile only ages, and stale commands are
        refused (command_gate.py), so the pause can never move the arm late.
        """
        link = self.config.link
        batch = self.sub.drain(link.max_messages_per_wake)
        if len(batch) >= link.max_messages_per_wake:
            self._commands_paused_until = now + round(link.command_backlog_pause_ms * 1e6)
            self.counters["command_backlog_pauses"] += 1
        newest: dict[str, tuple[Command, int | None]] = {}
        if self.lease is not None:
            self._handle_signed(batch, now, newest)
            batch = []
        for msg, t_recv in batch:
            if isinstance(msg, Heartbeat):
                self.clock.on_heartbeat(
                    msg.t_send_ns, msg.echo_t_send_ns, msg.echo_t_recv_ns, t_recv
                )
                self.gate.heard(msg.t_send_ns, t_recv, now)
            elif isinstance(msg, Command):
                self.counters["commands_received"] += 1
                refusal, sent = self.gate.admit(msg, t_recv, now)
                if refusal is not None:
                    self.counters[refusal] += 1
                    self._record_command(msg, f"refused: {refusal}")
                    continue
                if not self._latch_lets(msg, True, None, "operator", now):
                    continue
                device = "gripper" if msg.action.startswith("gripper") else "arm"
                older = newest.get(device)
                if older is not None:  # newest only: an older wish is never acted on
                    self.counters["commands_superseded"] += 1
                    self._record_command(older[0], "superseded")
                newest[device] = (msg, sent)
            elif isinstance(msg, VideoSignal):
                self._on_video_signal(msg, None)
            else:
                self.counters["messages_unexpected"] += 1
        if batch:
            self._video_heard_ns = now
        for device, (cmd, sent) in newest.items():
            self._dispatch(device, cmd, sent)
        self.counters["decode_errors"] = self.sub.rejected_total

    def _handle_signed(
        self,
        batch: list[tuple[Any, int]],
        now: int,
        newest: dict[str, tuple[Command, int | None]],
    ) -> None:
        """With a roster: each key its own clock and gate; only the lease holder commands.

        The codec has already checked every signature (a message whose ``sig``
        does not verify never gets here); what is left is whether its signer
        is one of ours, and whether it holds the lease.
        """
        lease = self.lease
        for msg, t_recv in batch:
            key = getattr(msg, "signer", None)
            if key is None:
                self.counters["messages_unsigned"] += 1
                continue
            peer = lease.peer(key)
            if peer is None:
                self.counters["messages_unknown_signer"] += 1
                continue
            peer.last_heard_ns = now
            if isinstance(msg, Heartbeat):
                peer.clock.on_heartbeat(
                    msg.t_send_ns, msg.echo_t_send_ns, msg.echo_t_recv_ns, t_recv
                )
                peer.gate.heard(msg.t_send_ns, t_recv, now)
                continue
            if isinstance(msg, VideoSignal):  # any role may watch: the roster vouched for it
                self._on_video_signal(msg, key)
                continue
            if not isinstance(msg, Command):
                self.counters["messages_unexpected"] += 1
                continue
            self.counters["commands_received"] += 1
            refusal, sent = peer.gate.admit(msg, t_recv, now)
            if refusal is not None:
                self.counters[refusal] += 1
                self._record_command(msg, f"refused: {refusal}")
                continue
            if msg.action in LEASE_ACTIONS:
                outcome = lease.handle(key, msg, now)
                self.counters[outcome] += 1
                self._record_command(msg, outcome)
                continue
            holder, who = key == lease.holder, peer.entry
            if not self._latch_lets(msg, holder, who.role, who.name, now):
                continue
            device = "gripper" if msg.action.startswith("gripper") else "arm"
            older = newest.get(device)
            if older is not None:
                self.counters["commands_superseded"] += 1
                self._record_command(older[0], "superseded")
            newest[device] = (msg, sent)
        timed_out = lease.tick(now)
        if timed_out is not None:
            self.counters[timed_out] += 1
        self._follow_lease(now, newest)

    def _latch_lets(self, msg: Command, holder: bool, role: str | None, who: str, now: int) -> bool:
        """The stop latch's word on an admitted command: True to act on it on the device.

        A refusal is counted and recorded with its reason; an ``arm_resume``
        is used up here (it moves nothing), an ``arm_stop`` latches and goes
        on to stop the arm.
        """
        latch = self.stop_latch
        refusal = latch.judge(msg.action, holder, role)
        if refusal is not None:
            self.counters[refusal] += 1
            self._record_command(msg, f"refused: {REFUSALS[refusal]}")
            return False
        if msg.action in ("arm_stop", "arm_resume"):
            if latch.apply(msg.action, who, now):
                self._heartbeat_now = True  # every operator sees the latch change at once
            self.counters["arm_stops_latched" if msg.action == "arm_stop" else "arm_resumes"] += 1
        if msg.action == "arm_resume":
            self._record_command(msg, "applied")
            return False
        return True

    def reload_roster(self, now: int) -> bool:
        """Read ``link.roster_file`` again; a broken file keeps the roster in force, and so
        does one that would remove every controller or every robot (``check_replacement``).

        A key added may act from its next message; a key removed is ignored
        from now on, and if it held the lease the arm stops (as at any change
        of holder).
        """
        path = self.config.link.roster_file
        if self.lease is None or path is None:
            log.warning("roster reload asked, but this robot has no link.roster_file")
            return False
        try:
            roster = load_roster(path)
            if self.roster is not None:
                check_replacement(self.roster, roster, path)
        except ConfigError as e:
            self.counters["roster_reloads_failed"] += 1
            log.error("roster reload failed, the roster in force stays: %s", e)
            return False
        self.roster = roster
        changes = self.lease.replace_roster(roster.by_signing_key())
        self.counters["roster_reloads"] += 1
        log.info(
            "roster %s reloaded: %d operator keys; %s",
            path,
            len(self.lease.operators),
            "; ".join(changes) or "nothing changed",
        )
        self._follow_lease(now, {})
        return True

    def _follow_lease(self, now: int, newest: dict[str, tuple[Command, int | None]]) -> None:
        """After the holder changed: the deadman follows the new holder, the arm stops once.

        Stopping at a hand-over means the new holder starts from rest, never
        from the old holder's last jog; its own commands in this batch still go.
        """
        lease = self.lease
        if lease.changes == self._lease_changes_seen:
            return
        self._lease_changes_seen = lease.changes
        self.gate = lease.holder_gate
        self._heartbeat_now = True
        if not any(cmd.action == "arm_jog" for cmd, _ in newest.values()):
            self._stop_devices(f"control lease now {lease.holder_name() or 'nobody'}'s")

    def _dispatch(self, device: str, cmd: Command, sent_ns: int | None) -> None:
        """Hand the command to its device's worker; a missing device refuses at once."""
        worker = self._workers.get(device)
        if worker is None:
            self.counters["commands_rejected"] += 1
            log.warning("command %s rejected: this scene has no %s", cmd.action, device)
            self._record_command(cmd, f"rejected: this scene has no {device}")
            return
        if device == "gripper":
            # the heartbeat names it, so the operator can resend a gripper command we never saw
            self._gripper_ack = (float(cmd.seq), float((cmd.session or 0) & SESSION_LOW_MASK))
            gripper = self.gripper
            if cmd.action == "gripper_open":
                call, args = gripper.open, ()
            elif cmd.action == "gripper_close":
                call, args = gripper.close_to_level, (cmd.grip_level or 16,)
            else:
                call, args = gripper.hold, ()
        elif cmd.action == "arm_jog" and cmd.velocity is not None:
            issued_s = None if sent_ns is None else sent_ns / 1e9
            call, args = self.arm.jog, (cmd.velocity, issued_s)
        else:
            call, args = self.arm.stop, ()
        on_done = self._make_on_done(cmd, sent_ns)
        worker.post(DeviceRequest(cmd.action, call, args, on_done))

    def _make_on_done(self, cmd: Command, sent_ns: int | None) -> Callable[..., None]:
        def on_done(request: DeviceRequest, result: Any, error: BaseException | None) -> None:
            if error is None:
                outcome = "applied"
            elif isinstance(error, (DeviceError, ValueError, DecodeError)):
                log.warning("command %s rejected: %s", cmd.action, error)
                outcome = f"rejected: {error}"
            else:
                log.error("command %s failed: %r", cmd.action, error)
                outcome = f"failed: {error!r}"
            sent = result if cmd.action == "arm_jog" and error is None else None
            self._record_command(cmd, outcome, sent, sent_ns)

        return on_done

    def _record_command(
        self, cmd: Command, outcome: str, sent: Any = None, sent_ns: int | None = None
    ) -> None:
        """``t_sent_ns`` (the operator's send time on our clock) is when the arm's jog
        deadline started counting, which an exporter needs to end the jog where the arm did."""
        if not self._recording:
            return
        self.recorder.write(
            "robot/command",
            self.now(),
            {
                "seq": cmd.seq,
                "action": cmd.action,
                "grip_level": cmd.grip_level,
                "velocity": list(cmd.velocity) if cmd.velocity else None,
                "sent_velocity": None if sent is None else [float(v) for v in sent],
                "t_sent_ns": sent_ns,
                "outcome": outcome,
            },
        )

    # -------------------------------------------------------------- video
    def _on_video_signal(self, msg: VideoSignal, signer: bytes | None) -> None:
        self.counters["video_signals_received"] += 1
        if self.video is None:
            self.counters["video_signals_unserved"] += 1
            if msg.kind == "offer":
                self._publish_video(
                    VideoSignal(
                        seq=0,
                        t_send_ns=0,
                        kind="closed",
                        viewer=msg.viewer,
                        reason="this robot serves no video (its link.video_url is empty)",
                    )
                )
            return
        self.video.on_signal(msg, signer)

    def _serve_video(self, now: int) -> None:
        """Publish the answers the video sessions produced; end the sessions of quiet viewers."""
        video = self.video
        if video.outgoing:
            for msg in video.take_outgoing():
                self._publish_video(msg)
        if now < self._next_video_expiry_ns:
            return
        self._next_video_expiry_ns = now + 1_000_000_000
        if video.sessions:
            video.expire(self._video_viewer_heard)

    def _video_viewer_heard(self, signer: bytes | None) -> bool:
        """Called on the video thread: a stale read of these times is harmless."""
        limit = round(self.config.link.video_viewer_timeout_s * 1e9)
        if signer is None or self.lease is None:
            last = self._video_heard_ns
        else:
            peer = self.lease.peer(signer)
            last = peer.last_heard_ns if peer is not None else 0
        return self.now() - last < limit

    def _publish_video(self, msg: VideoSignal) -> None:
        self._vsig_seq += 1
        msg.seq, msg.t_send_ns, msg.session = self._vsig_seq, self.now(), self.session
        self.pub.send(msg)
        self.counters[f"video_{msg.kind}s_sent"] += 1

    def _deadman_deadline_ns(self) -> int:
        """When the operator's silence stops the arm, if nothing fresh is heard before then."""
        heard = self.gate.last_fresh_ns
        if heard is None or self.link_state != "ok":
            return _NEVER_NS
        return heard + round(self.config.link.deadman_ms * 1e6) + 1

    def _check_deadman(self, now: int) -> None:
        """Counted from the newest fresh message's send time: a backlog cannot extend it."""
        heard = self.gate.last_fresh_ns
        fresh = heard is not None and (now - heard) / 1e6 <= self.config.link.deadman_ms
        new_state = "ok" if fresh else "down"
        if new_state != self.link_state:
            log.info("operator link %s -> %s", self.link_state, new_state)
            if new_state == "down" and heard is not None:
                self.counters["deadman_trips"] += 1
                self._stop_devices("operator silent")
                if self.lease is not None and self.lease.holder is not None:
                    self.counters["lease_expired"] += 1
                    self.lease.expire(now)
                    self._follow_lease(now, {})
            self.link_state = new_state
            self.link_changes.append((now, new_state))

    def _stop_devices(self, why: str) -> None:
        """Stop the arm and hold the gripper, through their workers (never waiting here)."""
        if self.arm is not None and "arm" in self._workers:
            self._workers["arm"].post(DeviceRequest("arm_stop", self.arm.stop))
            log.info("arm stopped: %s", why)
        if self.gripper is not None and "gripper" in self._workers:
            self._workers["gripper"].post(DeviceRequest("gripper_hold", self.gripper.hold))

    # ---------------------------------------------------------- heartbeat
    def _send_heartbeat(self) -> None:
        self._heartbeat_now = False
        self._hb_seq += 1
        if self._recording:
            stats = {"state": self.link_state, **self.stats()}
            self.recorder.write("robot/link", self.now(), stats)
        echo_send, echo_recv = self.clock.echo_fields()
        echo_signer = controller = pending = None
        if self.lease is not None:
            echo_signer, echo_send, echo_recv = self._next_echo()
            controller, pending = self.lease.holder, self.lease.pending
        msg = self._last_stim_msg
        self.pub.send(
            Heartbeat(
                seq=self._hb_seq,
                t_send_ns=self.now(),
                node="robot",
                state=self.link_state,
                echo_t_send_ns=echo_send,
                echo_t_recv_ns=echo_recv,
                stimulus_seq=msg.seq if msg else None,
                t_capture_ns=self._last_capture_ns if msg else None,
                stats=self._heartbeat_stats(),
                echo_signer=echo_signer,
                controller=controller,
                lease_pending=pending,
                session=self.session,
            )
        )

    def _next_echo(self) -> tuple[bytes | None, int | None, int | None]:
        """(key, echo fields) of the next operator heard in the last second, round robin.

        One heartbeat echoes one operator; taking turns gives each of five
        operators four clock samples a second, which its offset filter needs.
        """
        now = self.now()
        recent = [k for k, p in self.lease.peers.items() if now - p.last_heard_ns < 1_000_000_000]
        if not recent:
            return None, None, None
        self._echo_turn = (self._echo_turn + 1) % len(recent)
        key = recent[self._echo_turn]
        echo_send, echo_recv = self.lease.peers[key].clock.echo_fields()
        return key, echo_send, echo_recv

    def _heartbeat_stats(self) -> dict[str, float]:
        """``stats()``, cut to what a heartbeat may carry: the operator refuses a longer map."""
        stats = self.stats()
        if len(stats) > MAX_STATS:
            self._stats_cut(f"{len(stats)} counters, {MAX_STATS} sent: {sorted(stats)[MAX_STATS:]}")
            stats = dict(sorted(stats.items())[:MAX_STATS])
        return stats

    def stats(self) -> dict[str, float]:
        out = {k: float(v) for k, v in self.counters.items()}
        for name, worker in self._workers.items():  # counted on the workers' own threads
            c = worker.counters
            out["commands_applied"] = out.get("commands_applied", 0.0) + c["done"]
            out["commands_rejected"] = out.get("commands_rejected", 0.0) + c["failed"]
            out["commands_superseded"] = out.get("commands_superseded", 0.0) + c["superseded"]
            if c["poll_errors"]:
                out[f"{name}_poll_errors"] = float(c["poll_errors"])
        if self.video is not None:
            out.update((k, float(v)) for k, v in self.video.counters.items())
        if self._auth is not None and self._auth.refused:
            out["curve_refused"] = float(self._auth.refused)
        for name, rec in (("arm", self._arm_recovery), ("gripper", self._gripper_recovery)):
            if rec.device is not None:
                out[f"{name}_available"] = float(rec.available)
                out[f"{name}_reconnects"] = float(rec.recoveries)
        if self._first_seq is not None:
            out["frames_captured"] = float(self._last_seq - self._first_seq + 1)
        # the arm worker's latest reading, for the dashboard; while the arm reconnects what the
        # controller last said is no longer true (a speed, a pose): only the envelope is sent
        arm_state = self._arm_state
        if not self._arm_recovery.available:
            arm_state = {k: v for k, v in arm_state.items() if k.startswith(ARM_ENVELOPE_KEYS)}
        out.update(arm_state)
        out["arm_stop_latched"] = float(self.stop_latch.latched)
        if self._gripper_ack is not None:
            out["gripper_command_seq"], out["gripper_command_session"] = self._gripper_ack
        return out


def _wire_name(name: str) -> bytes:
    if not name:
        return b""
    try:
        return check_robot_name(name)
    except DecodeError as e:
        raise ConfigError(f"robot link.robot_name: {e}") from None


def compiled_step_for(classifier: Any, render: Any) -> Any:
    """``compiled_step.CompiledFrameStep`` where it applies (numba classifier, mask mode), or None.

    Here rather than in compiled_step.py: that module imports numba, which a
    node without the numba backend never needs.
    """
    if getattr(classifier, "numba_forward", None) is None:
        return None  # numba may not even be installed: import nothing
    try:
        from robot_side.compiled_step import CompiledFrameStep

        return CompiledFrameStep.for_node(classifier, render)
    except Exception as e:  # the plain path publishes the same stimuli, slower
        log.warning("compiled frame step unavailable (%s); using the plain path", e)
        return None


def build_robot_node(
    config: RobotConfig, ctx: zmq.Context | None = None, recorder: Recorder | None = None
) -> RobotNode:
    """Build the devices and classifier a config names, and nothing else."""
    from robot_side.arm import KINDS as ARM_KINDS
    from robot_side.gripper import KINDS as GRIPPER_KINDS
    from robot_side.tactile import KINDS as TACTILE_KINDS

    tactile = build_device(TACTILE_KINDS, config.tactile, "robot.tactile")
    gripper = _optional(GRIPPER_KINDS, config.gripper, "robot.gripper")
    arm = _optional(ARM_KINDS, config.arm, "robot.arm")
    classifier = None
    if config.render.mode == "mask":
        from robot_side.perception import load_classifier

        classifier = load_classifier(config.classifier.path, backend=config.classifier.backend)
    return RobotNode(
        config, tactile, classifier=classifier, gripper=gripper, arm=arm, ctx=ctx, recorder=recorder
    )


def _optional(registry: dict[str, str], section: dict[str, Any], where: str) -> Device | None:
    if section.get("kind", "none") == "none":
        return None
    return build_device(registry, section, where)
