"""The whole frame rule, from a tactile sample to the stimulus sent (or nothing).

The robot node, replay (deploy/replay/robot_check.py) and the skipping bench
(harness/bench/skipping.py) all drive frames through ``FramePipeline.offer``,
so the rate cap, the stale-frame test, the contact test, the no-contact and
identical-frame skips, the dead band and the keyframes are one piece of
code that the three cannot apply differently.

- **rate cap**: at most ``publish_rate_hz`` frames rendered a second (the
  interval is 0.9 of the period, so jitter never halves the rate); the
  loop sleeps through the frames the cap would drop (``frames_until_due``).
- **stale**: a frame older than ``max_frame_age_ms`` is not rendered.
- **skips** (frame_rule.py): no inference without contact, nothing
  recomputed for an identical frame.
- **dead band**: nothing resent while no cell changes between pressed and
  lifted and no force moves by more than ``deadband_n``.
- **keyframes**: the last stimulus again every ``keyframe_interval_ms``,
  which bounds the damage of a lost change. On the fabric a stimulus is a
  datagram, lost in bursts: the heartbeats that follow a lost change confirm
  a stimulus the operator never got, so its palm lifts 150 ms after the one
  before, unless a keyframe brings the change first. Where keyframes come
  more often than heartbeats (the fabric), a heartbeat counts as one for the
  interval: the keyframes fill the gaps between heartbeats instead of
  doubling them, so the operator hears the current stimulus confirmed every
  interval with a third fewer datagrams (``heartbeat_sent``).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable

import numpy as np

from common.recording.channels import Recorder
from common.wire.messages import Stimulus
from robot_side.node.config import RobotConfig
from robot_side.node.frame_rule import Classifier, FrameRenderer
from robot_side.tactile.base import TactileSample

#: how often an unchanged stimulus is sent again, by link mode. On the fabric: the operator
#: lifts the palm when what it renders was captured 150 ms ago and nothing since confirmed it;
#: after a lost change the heartbeats confirm the change, not what the operator has. The
#: keyframe that makes it good is captured up to a frame period (60 Hz) after this interval
#: and crosses the path (bad_day's p99 64.5 ms): 25 ms, half a heartbeat period (keyframes fill
#: between them), leaves room for a lost keyframe too
DIRECT_KEYFRAME_MS, FABRIC_KEYFRAME_MS = 500.0, 25.0


def keyframe_interval_ms(config: RobotConfig) -> float:
    """The config's keyframe interval, or the link mode's default."""
    if config.render.keyframe_interval_ms is not None:
        return config.render.keyframe_interval_ms
    return FABRIC_KEYFRAME_MS if config.link.mode == "fabric" else DIRECT_KEYFRAME_MS


class FramePipeline:
    """Frames in, stimuli out through ``send``; counts what it skipped and why."""

    def __init__(
        self,
        config: RobotConfig,
        classifier: Classifier | None,
        send: Callable[[Stimulus], bytes],
        *,
        now: Callable[[], int],
        session: int,
        counters: Counter[str] | None = None,
        recorder: Recorder | None = None,
        grip_level: Callable[[], int | None] = lambda: None,
    ) -> None:
        """``config``: its ``render``, ``publish_rate_hz`` and ``max_frame_age_ms``;
        ``recorder`` None records nothing."""
        self.render = config.render
        self.keyframe_ns = keyframe_interval_ms(config) * 1e6
        #: heartbeats confirm the stimulus too: where they are further apart than keyframes,
        #: a keyframe is due an interval after the last stimulus or heartbeat, whichever is last
        self._heartbeats_count = self.keyframe_ns < 1e9 / config.link.heartbeat_rate_hz
        self._last_heartbeat_ns = 0
        self.max_frame_age_ns = config.max_frame_age_ms * 1e6
        #: the rate cap: a frame is rendered at least this long after the last one
        self.min_interval_ns = round(0.9e9 / config.publish_rate_hz)
        self.send = send
        self.now = now
        self.session = session
        self.counters: Counter[str] = Counter() if counters is None else counters
        self.recorder = recorder
        self.grip_level = grip_level
        self.renderer = FrameRenderer(self.render, classifier, self.counters, recorder, now)
        self.first_seq: int | None = None
        self.last_seq = 0
        self._last_capture_seen: tuple[int, int] | None = None
        self._frame_period_ns = 0.0  # estimated from the frames' capture times
        self._skip_requested = 0
        self._last_process_ns: int | None = None  # None: no frame rendered yet
        self._last_cells: list[float] | None = None  # the last stimulus sent, row by row
        self._last_pattern: int | None = None
        self._last_publish_ns = 0
        self._seq = 0
        self.last_capture_ns: int | None = None  # of the last frame processed
        self.last_frame: np.ndarray | None = None  # the last frame processed
        #: the stimulus the operator renders now: the last one sent, keyframes included
        self.last_stimulus: Stimulus | None = None
        #: the last change sent (not a keyframe): what a heartbeat names as current, so that an
        #: operator that lost the keyframes since still has it confirmed (their cells are its)
        self.last_change: Stimulus | None = None

    # ------------------------------------------------------------ the rate cap
    def frames_until_due(self, now: int) -> int:
        """Frames that will arrive before the next render is due (0 before the rate is known).

        The caller may sleep through them; ``offer`` counts them as skipped by the cap.
        """
        period = self._frame_period_ns
        if not self.last_seq or period <= 0 or self._last_process_ns is None:
            self._skip_requested = 0
        else:
            remaining = self._last_process_ns + self.min_interval_ns - now
            self._skip_requested = max(0, int(remaining // period))
        return self._skip_requested

    def offer(self, sample: TactileSample, now: int) -> Stimulus | None:
        """One frame as it arrives: counted, then rendered if the rate cap lets it.

        ``now``: when the frame is judged (the cap, the age, its record). Returns the
        stimulus sent, if any.
        """
        self._account(sample)
        if self.rate_capped(now):
            self.counters["frames_skipped_rate"] += 1
            return None
        return self.process(sample, now)

    def rate_capped(self, now: int) -> bool:
        """Whether a frame offered at ``now`` comes too soon after the last one rendered."""
        last = self._last_process_ns
        return last is not None and now - last < self.min_interval_ns

    def _account(self, sample: TactileSample) -> None:
        last = self._last_capture_seen
        if last is not None and sample.seq > last[0]:
            interval = (sample.t_capture_ns - last[1]) / (sample.seq - last[0])
            if interval > 0:  # the sensor's frame period, smoothed
                p = self._frame_period_ns
                self._frame_period_ns = interval if p <= 0 else 0.9 * p + 0.1 * interval
        self._last_capture_seen = (sample.seq, sample.t_capture_ns)
        if self.first_seq is None:
            self.first_seq = sample.seq
        gap = max(0, sample.seq - self.last_seq - 1) if self.last_seq else 0
        slept = min(gap, self._skip_requested)  # frames deliberately not woken for
        self.counters["frames_skipped_rate"] += slept
        self.counters["frames_superseded"] += gap - slept
        self.last_seq = sample.seq

    # ---------------------------------------------------------- one frame
    def process(self, sample: TactileSample, now: int | None = None) -> Stimulus | None:
        """Render one frame the rate cap let through; send the stimulus if it changed.

        ``now`` defaults to the clock; a keyframe and a send are always timed by the clock.
        """
        if now is None:
            now = self.now()
        self._last_process_ns = now
        if now - sample.t_capture_ns > self.max_frame_age_ns:
            self.counters["frames_stale"] += 1
            return None
        self.counters["frames_processed"] += 1
        self.last_capture_ns = sample.t_capture_ns
        self.last_frame = sample.frame  # the assist reads the band's finer angle from it
        truth = sample.truth.pattern if sample.truth is not None else None
        outcome = self.renderer.rendered(sample, now, truth)
        if outcome is None:
            self.counters["frames_identical"] += 1
            return self._maybe_keyframe(sample)
        contact, cells, pattern, confidence = outcome
        if not self._changed(cells, pattern):
            self.counters["stimuli_unchanged"] += 1
            return self._maybe_keyframe(sample)
        return self._publish(sample, cells, contact, pattern, confidence, truth, keyframe=False)

    def resend_next(self) -> None:
        """Render and send the next frame whatever was sent before (benchmarks force each one)."""
        self._last_cells = None
        self.renderer.forget()

    def _changed(self, cells: list[float], pattern: int | None) -> bool:
        """Another set of pressed cells, or a force moved by more than the dead band."""
        last = self._last_cells
        if last is None or pattern != self._last_pattern:
            return True
        deadband = self.render.deadband_n
        return any(
            (new > 0) != (old > 0) or abs(new - old) > deadband
            for new, old in zip(cells, last, strict=True)
        )

    def heartbeat_sent(self, now: int) -> None:
        """A heartbeat confirming ``last_stimulus`` went out at ``now``."""
        if self._heartbeats_count and self.last_stimulus is not None:
            self._last_heartbeat_ns = now

    def _maybe_keyframe(self, sample: TactileSample) -> Stimulus | None:
        msg = self.last_stimulus
        confirmed = max(self._last_publish_ns, self._last_heartbeat_ns)
        if msg is None or self.now() - confirmed < self.keyframe_ns:
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
        self._seq += 1
        now = self.now()
        msg = Stimulus(
            seq=self._seq,
            t_send_ns=now,
            t_capture_ns=sample.t_capture_ns,
            frame_seq=sample.seq,
            mode=self.render.mode,
            contact=contact,
            stimulus=np.array(cells, np.float32).reshape(3, 3),
            pattern=pattern,
            confidence=confidence,
            grip_level=self.grip_level(),
            keyframe=keyframe,
            sim_truth_pattern=truth,
            session=self.session,
        )
        data = self.send(msg)
        if self.recorder is not None:
            self.recorder.write("robot/stimulus", now, {"seq": msg.seq, "wire": data})
        self._last_cells = cells
        self._last_pattern = pattern
        self.last_stimulus = msg
        if not keyframe:
            self.last_change = msg
        self._last_publish_ns = now
        self.counters["keyframes" if keyframe else "stimuli_published"] += 1
        return msg
