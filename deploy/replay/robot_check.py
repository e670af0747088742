"""A robot recording replayed: its frames through the robot node's own pipeline again."""

from __future__ import annotations

import dataclasses
import logging
from typing import Any

import numpy as np

from common.wire.codec import DecodeError, decode
from common.wire.messages import Stimulus
from deploy.replay.recorded import Report

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class RecordedPrediction:
    """A ``robot/prediction`` record, in the shape the node reads of a prediction."""

    pattern: int
    confidence: float
    angle_probs: tuple[float, ...] = ()
    position_probs: tuple[float, ...] = ()


class RecordedPredictions:
    """A classifier that answers with the predictions the recording holds (``--no-classifier``)."""

    def __init__(self) -> None:
        self.current: RecordedPrediction | None = None  # for the frame being replayed

    def predict_one(self, frame: np.ndarray) -> RecordedPrediction | None:
        return self.current


class RobotReplay:
    """Recorded frames through the robot node's own ``FramePipeline``, compared with what it sent.

    The node is built from the recorded config and handed a virtual clock and
    a capture link, so the frame rule, the rate cap, the identical-frame skip,
    the dead band and the keyframes are checked by the code that made them.
    Each frame is offered at its recorded time (when the node rendered it: the
    rate cap and the age judge it then), with the clock at its stimulus's
    send time when one was sent for it: the node decided on a keyframe
    between the two, so a keyframe is due at the second exactly when it was
    due then. Only rendered frames are recorded, so a recorded frame the rate
    cap would have skipped is a mismatch.
    """

    def __init__(self, config: Any, atol: float, use_classifier: bool, report: Report) -> None:
        from common.clocks.clock import VirtualClock
        from common.wire.transport import CaptureLink
        from robot_side.node import RobotNode

        self.config = config
        self.render = config.render
        self.atol = atol
        self.report = report
        self.classifier = None
        if self.render.mode == "mask" and use_classifier:
            try:
                from robot_side.perception import load_classifier

                self.classifier = load_classifier(
                    config.classifier.path, backend=config.classifier.backend
                )
            except Exception as e:  # a missing model or backend: fall back, and say so
                log.warning("cannot load the classifier (%s); using the recorded patterns", e)
        self.reclassified = self.classifier is not None
        self.recorded = RecordedPredictions()
        if self.render.mode == "mask" and self.classifier is None:
            classifier: Any = self.recorded
        else:
            classifier = self.classifier
        self.clock = VirtualClock(0)
        self.link = CaptureLink()
        self.node = RobotNode(config, None, classifier=classifier, now=self.clock, link=self.link)
        self.frame: dict[str, Any] | None = None  # the frame waiting for its records
        self.frame_t_ns = 0
        self.prediction: dict[str, Any] | None = None
        self.sent: Stimulus | None = None  # what the node sent for that frame
        self.last_pattern: int | None = None  # of the last stimulus sent

    def feed(self, channel: str, record: dict[str, Any], t_ns: int = 0) -> None:
        if channel == "robot/frame":
            try:
                self.finish()  # a frame's prediction and stimulus come before the next frame
            finally:
                self.frame, self.frame_t_ns = record, t_ns
        elif channel == "robot/prediction":
            if self.frame is not None and int(record["frame_seq"]) == int(self.frame["frame_seq"]):
                self.prediction = record
        elif channel == "robot/stimulus":
            self._stimulus(record)
        elif channel == "robot/link":  # a heartbeat: it confirms the stimulus, as keyframes do
            self.finish()  # the frame before it was rendered and sent before it
            self.node.pipeline.heartbeat_sent(t_ns)

    def _stimulus(self, record: dict[str, Any]) -> None:
        try:
            msg = decode(record["wire"])
        except (DecodeError, KeyError, TypeError) as e:
            self.report.mismatch("stimulus_wire", f"record seq {record.get('seq')}: {e}")
            return
        if not isinstance(msg, Stimulus):
            self.report.mismatch("stimulus_wire", f"seq {msg.seq} is a {type(msg).TYPE}")
            return
        if msg.mode != self.render.mode:
            self.report.mismatch(
                "mode", f"seq {msg.seq} sent {msg.mode!r}, the config says {self.render.mode!r}"
            )
        if self.frame is not None and msg.frame_seq == int(self.frame["frame_seq"]):
            self.sent = msg
        else:
            self.report.ok("stimuli_without_frame")  # the frame's record was dropped
            self.last_pattern = msg.pattern

    def finish(self) -> None:
        """Replay the waiting frame through the node and compare what both sent for it."""
        from robot_side.tactile.base import GraspTruth, TactileSample

        record, sent = self.frame, self.sent
        if record is None:
            return
        self.frame, self.sent = None, None
        seq = int(record["frame_seq"])
        # what the node knew and the recording only shows in the stimulus it sent
        truth = sent.sim_truth_pattern if sent is not None else self.last_pattern
        self.recorded.current = self._recorded_prediction(self.prediction, sent)
        self.prediction = None
        self.clock.t_ns = sent.t_send_ns if sent is not None else self.frame_t_ns
        n = len(self.link.messages)
        pipeline = self.node.pipeline
        # the frame is judged at its recorded time (rate cap, age), as the node judged it
        if pipeline.rate_capped(self.frame_t_ns):
            self.report.mismatch(
                "rate_cap", f"frame {seq}: rendered sooner after the last than the rate cap allows"
            )
        pipeline.offer(
            TactileSample(
                frame=np.asarray(record["frame"], dtype=np.float32),
                seq=seq,
                t_capture_ns=int(record["t_capture_ns"]),
                truth=GraspTruth(pattern=truth, grip_level=None),
            ),
            self.frame_t_ns,
        )
        replayed = self.link.messages[n] if len(self.link.messages) > n else None
        self.report.ok("frames_replayed")
        if sent is not None:
            self.last_pattern = sent.pattern
        self._compare(seq, sent, replayed)

    def _compare(self, frame_seq: int, sent: Stimulus | None, replayed: Any) -> None:
        if sent is None and replayed is None:
            return
        if sent is None or replayed is None:
            one = sent or replayed
            kind = "keyframe" if one.keyframe else "stimulus"
            who = "the node sent" if replayed is None else "the replay sends"
            self.report.mismatch(kind, f"frame {frame_seq}: only {who} a {kind}")
            return
        if sent.keyframe != replayed.keyframe:
            self.report.mismatch(
                "keyframe",
                f"seq {sent.seq}: keyframe {sent.keyframe}, replayed {replayed.keyframe}",
            )
            return
        if sent.contact != replayed.contact:
            self.report.mismatch(
                "contact", f"seq {sent.seq}: sent {sent.contact}, replayed {replayed.contact}"
            )
            return
        if sent.pattern != replayed.pattern:
            how = "classified" if self.reclassified else "recorded prediction"
            self.report.mismatch(
                "pattern", f"seq {sent.seq}: sent {sent.pattern}, {how} {replayed.pattern}"
            )
        elif self.reclassified and sent.contact and not sent.keyframe:
            self.report.ok("patterns_matching")
        err = float(np.abs(replayed.stimulus - sent.stimulus).max())
        if err > self.atol:
            self.report.mismatch(
                "keyframe" if sent.keyframe else "stimulus",
                f"seq {sent.seq} (frame {frame_seq}): off by {err:.3g} N; "
                f"sent {sent.stimulus.round(3).tolist()}, "
                f"rendered {replayed.stimulus.round(3).tolist()}",
            )
        else:
            self.report.ok("keyframes_matching" if sent.keyframe else "stimuli_matching")

    def _recorded_prediction(
        self, record: dict[str, Any] | None, sent: Stimulus | None
    ) -> RecordedPrediction | None:
        """What the classifier said of the frame, as recorded (or as the stimulus shows)."""
        if record is not None:
            return RecordedPrediction(
                int(record["pattern"]),
                float(record["confidence"]),
                tuple(float(p) for p in record["angle_probs"]),
                tuple(float(p) for p in record["position_probs"]),
            )
        pattern = sent.pattern if sent is not None else self.last_pattern
        if pattern is None:
            return None
        confidence = sent.confidence if sent is not None else None
        return RecordedPrediction(pattern, 1.0 if confidence is None else confidence)
