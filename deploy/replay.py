"""``deepxpalm replay FILE``: feed a recording back through the pipeline.

A robot recording: every recorded frame goes through the robot node's own
``process`` again (classified again in mask mode, when the classifier
loads), at its recorded time, and what the node sends is compared with what
it sent then: the frame rule, the dead band and the keyframes are checked.
An operator recording: every received stimulus is rendered again through
the LinkGlide renderer, and each recorded servo write must be one
rate-limited step from the previous write toward that stimulus's goal, or
toward the lifted pose (the stimulus went stale), every count inside the
calibrated limits. Both use the node's
effective config stored in the recording, so a change of code or defaults
since the session shows up as a mismatch.

``--publish`` sends the recorded stimuli (and frames) again on a PUB socket
at their recorded pace, with fresh timestamps and heartbeats that keep the
current stimulus confirmed, so a live operator node or a dashboard can be
driven from a recording.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import json
import logging
import threading
import time
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from common.codec import DecodeError, decode, encode
from common.config import from_dict
from common.errors import ConfigError
from common.messages import Heartbeat, Stimulus, TactileFrame
from common.tactile import SATURATION_N

log = logging.getLogger(__name__)

FRAME_WINDOW = 512  # frames kept to match stimuli that come later (a stimulus follows its frame)
MAX_EXAMPLES = 10  # mismatches described in the report; all are counted


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", type=Path, help="robot.mcap or operator.mcap from --record")
    parser.add_argument(
        "--check", action="store_true", help="exit 1 when anything does not match the recording"
    )
    parser.add_argument(
        "--atol",
        type=float,
        default=1e-5,
        help="newtons a re-rendered stimulus cell may differ by (default 1e-5: float32 rounding)",
    )
    parser.add_argument(
        "--no-classifier",
        action="store_true",
        help="mask mode: trust the recorded patterns instead of classifying the frames again",
    )
    parser.add_argument(
        "--publish",
        metavar="ENDPOINT",
        help="also send the recorded stimuli on a PUB bound here, e.g. tcp://127.0.0.1:5555",
    )
    parser.add_argument(
        "--speed", type=float, default=1.0, help="publishing pace; 2 = twice as fast (default 1)"
    )
    parser.add_argument(
        "--wait-subscriber",
        type=float,
        default=5.0,
        metavar="S",
        help="with --publish: wait this long for a subscriber before sending (default 5)",
    )
    parser.add_argument(
        "--calibration",
        type=Path,
        metavar="FILE",
        help="operator: the servo calibration TOML, when the recorded one is not on this machine",
    )
    parser.add_argument(
        "--recover",
        type=Path,
        metavar="OUT",
        help="only copy FILE (from a killed node) to OUT with the index Foxglove wants, and exit",
    )
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")


# ------------------------------------------------------------------ config
def recorded_config(metadata: dict[str, dict[str, str]], node: str) -> Any:
    """The node's effective config as the recording stored it (defaults if absent)."""
    if node == "robot":
        from robot_side.config import RobotConfig as cls
    else:
        from operator_side.config import OperatorConfig as cls
    text = metadata.get("deepxpalm.node", {}).get("config_toml")
    if text is None:
        log.warning("the recording holds no config; checking against today's defaults")
        return cls()
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"the config stored in the recording does not parse: {e}") from None
    return from_dict(cls, data.get(node, data), where=node)


def node_of(path: Path, metadata: dict[str, dict[str, str]]) -> str:
    node = metadata.get("deepxpalm.node", {}).get("node")
    if node in ("robot", "operator"):
        return node
    from common.mcap_recorder import read_recording

    for channel, _, _ in read_recording(path):
        prefix = channel.split("/", 1)[0]
        if prefix in ("robot", "operator"):
            return prefix
    raise ConfigError(f"{path} holds no robot/ or operator/ channel: is it a DeepXPalm recording?")


class Report:
    """Counts and the first few mismatches, per kind."""

    def __init__(self) -> None:
        self.counts: collections.Counter[str] = collections.Counter()
        self.examples: list[str] = []

    def ok(self, what: str) -> None:
        self.counts[what] += 1

    def mismatch(self, what: str, detail: str) -> None:
        self.counts[f"mismatch_{what}"] += 1
        if len(self.examples) < MAX_EXAMPLES:
            self.examples.append(f"{what}: {detail}")

    @property
    def mismatches(self) -> int:
        return sum(v for k, v in self.counts.items() if k.startswith("mismatch_"))


# ----------------------------------------------------------- robot check
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
        from common.clock import VirtualClock
        from common.transport import CaptureLink
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


# -------------------------------------------------------- operator check
class OperatorReplay:
    """Stimuli -> LinkGlide goals; each recorded write must be one legal step toward them."""

    def __init__(self, config: Any, report: Report, calibration_file: Path | None = None) -> None:
        from operator_side.palm.renderer import LinkGlideRenderer

        self.calibration = calibration_for(config, calibration_file)
        self.renderer = LinkGlideRenderer(config.renderer, self.calibration)
        self.report = report
        self.target: np.ndarray | None = None  # goal counts of the newest stimulus
        self.prev: np.ndarray | None = None
        self.pending_jump: tuple[np.ndarray, np.ndarray] | None = None
        self.calibration_checked = False

    def feed(self, channel: str, record: dict[str, Any], t_ns: int = 0) -> None:
        if channel == "operator/stimulus":
            try:
                msg = decode(record["wire"])
            except (DecodeError, KeyError, TypeError) as e:
                self.report.mismatch("stimulus_wire", str(e))
                return
            if isinstance(msg, Stimulus):
                self.target = self.renderer.target_counts(msg.stimulus)
                self.report.ok("stimuli_rendered")
        elif channel == "operator/servo_goals":
            self._write(record)

    def _write(self, record: dict[str, Any]) -> None:
        counts = np.asarray(record["counts"])
        cal = self.calibration
        if counts.shape != (6,) or counts.dtype.kind not in "iu":
            self.report.mismatch("servo_goal", f"counts {counts!r} are not 6 integers")
            return
        if not cal.within_limits(counts):
            self.report.mismatch("servo_limits", f"counts {counts.tolist()} outside the limits")
        if not self.calibration_checked and record.get("angles") is not None:
            self.calibration_checked = True
            angles = np.asarray(record["angles"], dtype=np.float64)
            if not np.allclose(cal.counts_to_angles(counts), angles, atol=1e-9):
                log.warning(
                    "the recorded angles do not fit this calibration: pass --calibration FILE"
                )
                self.report.mismatch("calibration", "recorded angles do not fit the calibration")
        prev, self.prev = self.prev, counts
        if self.pending_jump is not None:  # a jump is legal only as the very last write
            self.report.mismatch("servo_step", f"jump {self.pending_jump[0].tolist()} -> ...")
            self.pending_jump = None
        retract = self.renderer.retract_counts
        if prev is None:
            if np.array_equal(counts, retract):
                self.report.ok("servo_writes_consistent")
            else:
                self.report.mismatch("servo_step", f"first write {counts.tolist()} is not lifted")
            return
        targets = [retract] if self.target is None else [self.target, retract]
        limit = self.renderer.max_step_counts
        if any(_is_step(prev, counts, t, limit) for t in targets):
            self.report.ok("servo_writes_consistent")
        elif np.array_equal(counts, retract):
            self.pending_jump = (prev, counts)  # the shutdown lift-off, if nothing follows
        else:
            self.report.mismatch(
                "servo_step",
                f"{prev.tolist()} -> {counts.tolist()} is no step of at most {limit} counts "
                f"toward {targets[0].tolist()} or the lifted pose",
            )

    def finish(self) -> None:
        if self.pending_jump is not None:
            self.report.ok("shutdown_lift_offs")


def _is_step(prev: np.ndarray, nxt: np.ndarray, target: np.ndarray, max_step: int) -> bool:
    """Whether ``nxt`` is ``renderer.step(prev, target, f)`` for some fraction f in (0, 1]."""
    delta = nxt.astype(np.int64) - prev
    need = target.astype(np.int64) - prev
    if np.any(np.abs(delta) > max_step) or np.any(delta * need < 0):
        return False
    if np.any(np.abs(delta) > np.abs(need)):
        return False
    clipped = np.abs(delta) < np.abs(need)
    if not clipped.any():
        return True
    step = np.abs(delta[clipped])
    return bool(np.all(step == step[0]) and np.all(np.abs(need[~clipped]) <= step[0]))


def calibration_for(config: Any, calibration_file: Path | None) -> Any:
    """The servo calibration an operator recording was made with, as far as it can be found."""
    from operator_side.servos.calibration import LinkGlideCalibration, load_calibration

    if calibration_file is not None:
        return load_calibration(calibration_file)
    servos = dict(config.servos)
    if servos.get("calibration_file"):
        path = Path(servos["calibration_file"])
        if path.exists():
            return load_calibration(path)
        log.warning("the recorded calibration file %s is not here; using the inline one", path)
    if "calibration" in servos:
        return from_dict(LinkGlideCalibration, servos["calibration"], where="servos.calibration")
    return LinkGlideCalibration()


# ------------------------------------------------------------------ check
def check(
    path: Path,
    *,
    atol: float = 1e-5,
    use_classifier: bool = True,
    calibration_file: Path | None = None,
) -> dict[str, Any]:
    """Replay ``path`` through the pipeline; the summary that ``run`` prints."""
    from common.mcap_recorder import RecordingReader, read_metadata

    metadata = read_metadata(path)
    node = node_of(path, metadata)
    config = recorded_config(metadata, node)
    report = Report()
    if node == "robot":
        replay: RobotReplay | OperatorReplay = RobotReplay(config, atol, use_classifier, report)
    else:
        replay = OperatorReplay(config, report, calibration_file)
    reader = RecordingReader(path)
    channels: collections.Counter[str] = collections.Counter()
    t_first = t_last = None
    for channel, t_ns, record in reader:
        channels[channel] += 1
        t_first = t_ns if t_first is None else t_first
        t_last = t_ns
        try:
            replay.feed(channel, record, t_ns)
        except (KeyError, TypeError, ValueError) as e:
            report.mismatch("record", f"{channel} at {t_ns}: {type(e).__name__}: {e}")
    try:
        replay.finish()
    except (KeyError, TypeError, ValueError) as e:
        report.mismatch("record", f"the last frame: {type(e).__name__}: {e}")
    summary: dict[str, Any] = {
        "file": str(path),
        "node": node,
        "closed_cleanly": reader.complete,
        "truncated": reader.truncated,
        "duration_s": None if t_first is None else round((t_last - t_first) / 1e9, 3),
        "records": dict(sorted(channels.items())),
        "checked": {k: v for k, v in sorted(report.counts.items()) if not k.startswith("mis")},
        "mismatches": report.mismatches,
        "mismatch_kinds": {
            k[len("mismatch_") :]: v
            for k, v in sorted(report.counts.items())
            if k.startswith("mismatch_")
        },
        "examples": report.examples,
    }
    if node == "robot":
        summary["render_mode"] = config.render.mode
        summary["classifier_rerun"] = replay.reclassified
    return summary


# ---------------------------------------------------------------- publish
def publish(
    path: Path,
    endpoint: str,
    *,
    speed: float = 1.0,
    stop: threading.Event | None = None,
    wait_subscriber_s: float = 5.0,
    heartbeat_rate_hz: float = 20.0,
    frame_rate_hz: float = 15.0,
) -> dict[str, int]:
    """Send the recorded stimuli (and frames) again at their recorded pace."""
    import zmq

    from common.clock import now_ns
    from common.mcap_recorder import read_recording
    from common.security import SecurityConfig, check_endpoint

    if not speed > 0:
        raise ConfigError(f"--speed must be positive, not {speed}")
    check_endpoint(endpoint, SecurityConfig())  # plain TCP: loopback only
    stop = stop or threading.Event()
    ctx = zmq.Context()
    sock = ctx.socket(zmq.XPUB)  # a PUB that also hears subscriptions: no slow-joiner loss
    sock.setsockopt(zmq.LINGER, 0)
    sent = collections.Counter()
    try:
        sock.bind(endpoint)
        if sock.poll(int(wait_subscriber_s * 1000)):
            sock.recv()  # the subscription itself
            time.sleep(0.05)
        else:
            log.warning(
                "no subscriber on %s after %.0f s; sending anyway", endpoint, wait_subscriber_s
            )
        hb_period = round(1e9 / heartbeat_rate_hz)
        frame_period = round(1e9 / frame_rate_hz) if frame_rate_hz > 0 else None
        t0_rec: int | None = None
        t0 = now_ns()
        next_hb = t0
        next_frame = t0
        hb_seq = frame_msg_seq = 0
        current: Stimulus | None = None

        def heartbeats_until(deadline: int) -> None:
            nonlocal next_hb, hb_seq
            while not stop.is_set():
                now = now_ns()
                if now >= deadline:
                    return
                if now >= next_hb:
                    hb_seq += 1
                    hb = Heartbeat(
                        seq=hb_seq,
                        t_send_ns=now,
                        node="robot",
                        state="ok",
                        stimulus_seq=None if current is None else current.seq,
                        t_capture_ns=None if current is None else now,
                    )
                    sock.send(encode(hb), zmq.NOBLOCK)
                    sent["heartbeats"] += 1
                    next_hb = now + hb_period
                while sock.poll(0):
                    sock.recv()  # subscriptions coming and going
                time.sleep(max(0.0, min(deadline, next_hb) - now_ns()) / 1e9)

        for channel, t_ns, record in read_recording(path):
            if stop.is_set():
                break
            kind = channel.split("/", 1)[-1]
            if kind not in ("stimulus", "frame"):
                continue
            t0_rec = t_ns if t0_rec is None else t0_rec
            heartbeats_until(t0 + round((t_ns - t0_rec) / speed))
            now = now_ns()
            if kind == "stimulus":
                try:
                    msg = decode(record["wire"])
                except (DecodeError, KeyError, TypeError):
                    sent["undecodable"] += 1
                    continue
                if not isinstance(msg, Stimulus):
                    continue
                age = max(0, msg.t_send_ns - msg.t_capture_ns)
                msg.t_send_ns, msg.t_capture_ns = now, max(0, now - age)
                sock.send(encode(msg), zmq.NOBLOCK)
                current = msg
                sent["stimuli"] += 1
            elif frame_period is not None and now >= next_frame:
                frame_msg_seq += 1
                raw = np.nan_to_num(record["frame"])
                frame = np.clip(raw, 0.0, SATURATION_N).astype(np.float32)
                msg = TactileFrame(
                    seq=frame_msg_seq,
                    t_send_ns=now,
                    t_capture_ns=now,
                    frame_seq=int(record["frame_seq"]),
                    frame=frame,
                )
                sock.send(encode(msg), zmq.NOBLOCK)
                sent["frames"] += 1
                next_frame = now + frame_period
    finally:
        sock.close(0)
        ctx.term()
    return dict(sent)


# -------------------------------------------------------------------- CLI
def run(args: argparse.Namespace) -> int:
    from common.cli_support import stop_on_signals

    if args.recover:
        from common.mcap_recorder import recover_recording

        n = recover_recording(args.file, args.recover)
        print(f"{args.recover}: {n} messages recovered from {args.file}, with an index")
        return 0

    summary = check(
        args.file,
        atol=args.atol,
        use_classifier=not args.no_classifier,
        calibration_file=args.calibration,
    )
    if args.publish:
        stop = stop_on_signals()
        summary["published"] = publish(
            args.file,
            args.publish,
            speed=args.speed,
            stop=stop,
            wait_subscriber_s=args.wait_subscriber,
        )
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        _print(summary)
    return 1 if args.check and summary["mismatches"] else 0


def _print(s: dict[str, Any]) -> None:
    state = "closed cleanly" if s["closed_cleanly"] else "cut short (read up to the last chunk)"
    dur = s["duration_s"]
    print(f"{s['file']}: {s['node']} recording, {state}, {dur if dur is not None else 0:.1f} s")
    for channel, n in s["records"].items():
        print(f"  {channel:24s} {n:8d} records")
    for what, n in s["checked"].items():
        print(f"  checked {what:32s} {n:8d}")
    if s.get("render_mode") == "mask":
        how = "classified again" if s["classifier_rerun"] else "taken from the recording"
        print(f"  patterns {how}")
    if s["mismatches"]:
        print(f"  {s['mismatches']} MISMATCHES: " + json.dumps(s["mismatch_kinds"]))
        for ex in s["examples"]:
            print(f"    {ex}")
    else:
        print("  no mismatches")
    if "published" in s:
        print("  published: " + ", ".join(f"{k} {v}" for k, v in s["published"].items()))
