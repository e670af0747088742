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

The recording's own word (``recorded``), the robot's replay
(``robot_check``), the operator's (``operator_check``) and publishing
(``publish``) are modules of their own; this one is the command.
"""

from __future__ import annotations

import argparse
import collections
import json
import logging
from pathlib import Path
from typing import Any

from deploy.replay.operator_check import OperatorReplay, calibration_for
from deploy.replay.publish import publish
from deploy.replay.recorded import Report, node_of, recorded_config
from deploy.replay.robot_check import RobotReplay

__all__ = ["add_arguments", "calibration_for", "check", "publish", "recorded_config", "run"]

log = logging.getLogger(__name__)


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


def check(
    path: Path,
    *,
    atol: float = 1e-5,
    use_classifier: bool = True,
    calibration_file: Path | None = None,
) -> dict[str, Any]:
    """Replay ``path`` through the pipeline; the summary that ``run`` prints."""
    from common.recording.mcap_recorder import RecordingReader, read_metadata

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


def run(args: argparse.Namespace) -> int:
    from common.process.command_line import stop_on_signals

    if args.recover:
        from common.recording.mcap_recorder import recover_recording

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
