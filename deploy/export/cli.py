"""``deepxpalm export``: recorded sessions -> one LeRobot dataset (format v3).

Typical uses::

    deepxpalm export runs/today --out datasets/today             # one episode per grasp
    deepxpalm export runs/mon runs/tue --out ds --episodes session --fps 60
    deepxpalm export runs/today --out ds2 --exclude 3,7 --task-file tasks.toml
"""

from __future__ import annotations

import argparse
import dataclasses
import heapq
import json
import logging
import sys
import time
from pathlib import Path
from typing import Any

from common.config.typed import from_dict, load_toml

log = logging.getLogger(__name__)

#: exit status when a recording was damaged: the dataset holds every intact chunk and the
#: summary lists what was lost; ``--accept-damage`` makes it 0
EXIT_DAMAGED = 3


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from deploy.export.resample import ExportConfig

    d = ExportConfig()
    parser.add_argument(
        "sessions",
        type=Path,
        nargs="+",
        help="session folders (robot.mcap, operator.mcap), folders of them, or robot .mcap files",
    )
    parser.add_argument("--out", type=Path, required=True, help="new dataset folder")
    parser.add_argument("--config", type=Path, help="TOML file with an [export] table")
    parser.add_argument("--fps", type=int, help=f"rows per second (default {d.fps})")
    parser.add_argument(
        "--episodes",
        choices=["grasp", "session"],
        help=f"one episode per grasp or per session (default {d.episodes})",
    )
    parser.add_argument(
        "--task",
        help=f"task string of episodes given none while recording or in --task-file "
        f"(default {d.task!r})",
    )
    parser.add_argument(
        "--exclude",
        type=_numbers,
        metavar="N,N",
        help="episode numbers to leave out, as an export of the same recordings without "
        "--exclude numbers them (e.g. 3,7)",
    )
    parser.add_argument(
        "--task-file",
        help='TOML file of NUMBER = "task" lines: the task of each episode (same numbering), '
        "over the tasks marked while recording and --task",
    )
    parser.add_argument(
        "--drop-failed",
        action="store_true",
        default=None,
        help="leave out the episodes marked failed while recording (default: kept, with "
        "next.success false)",
    )
    parser.add_argument(
        "--no-progress",
        action="store_true",
        help="no progress on stderr (a bar on a terminal, else a line per tenth of the work)",
    )
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.add_argument(
        "--accept-damage",
        action="store_true",
        help=f"exit 0 when a recording was damaged (default: exit {EXIT_DAMAGED}); the summary "
        "lists what was lost either way",
    )


def export(
    paths: list[Path], out: Path, config: Any = None, *, progress: bool = False
) -> dict[str, Any]:
    """Export the sessions under ``paths`` into a new dataset at ``out``; a summary."""
    from common.recording.episode_marks import read_marks
    from deploy.export.curation import Curator, load_task_file, verdicts
    from deploy.export.lerobot_v3 import LeRobotV3Writer
    from deploy.export.resample import ExportConfig
    from deploy.export.schema import features_for, image_feature
    from deploy.export.session import ExportError, find_sessions, scan

    config = config or ExportConfig()
    t_start, cpu_start = time.monotonic(), time.process_time()
    tasks = load_task_file(config.task_file) if config.task_file else {}
    _check_out(out)
    sessions = [scan(s) for s in find_sessions(paths)]
    groups = {"core"}
    for group, channel in (("arm", "robot/arm"), ("gripper", "robot/gripper")):
        have = [channel in s.channels for s in sessions]
        if all(have):
            groups.add(group)
        elif any(have):
            log.warning("only some sessions recorded %s: its features are left out", channel)
    if {"arm", "gripper"} <= groups:
        groups.add("state")
    cameras = _common_cameras(sessions)
    features = features_for(groups) + [
        image_feature(key, *sessions[0].cameras[key][1]) for key in cameras
    ]
    writer = LeRobotV3Writer(out, features, config.fps, video_codec=config.video_codec)
    total_s = sum(s.metadata["duration_s"] for s in sessions)
    bar = _bar(total_s, progress)
    first_t: list[int] = []
    meta_json = ""
    session_name = ""

    def begin(task: str, extra: dict[str, Any]) -> None:
        first_t.clear()
        writer.begin_episode(
            task, {"deepxpalm/session": session_name, "deepxpalm/metadata": meta_json, **extra}
        )

    def add(row: dict[str, Any]) -> None:
        if not first_t:
            first_t.append(row["t_ns"])
            writer.ep["deepxpalm/t_first_ns"] = row["t_ns"]
        writer.add(row)

    curator = Curator(
        default_task=config.task,
        exclude=config.exclude,
        tasks=tasks,
        drop_failed=config.drop_failed,
        begin=begin,
        add=add,
        end=writer.end_episode,
    )
    marks_read = marks_unplaced = marks_early = records = 0
    for session in sessions:
        meta_json = json.dumps(session.metadata, sort_keys=True, default=str)
        session_name = session.name
        marks, unplaced = read_marks(session.operator) if session.operator else ([], 0)
        marks_read += len(marks) + unplaced
        marks_unplaced += unplaced
        if unplaced:
            log.warning(
                "%s: %d episode mark(s) left unapplied: the recording holds no clock offset to "
                "the robot (the operator never heard it)",
                session.operator,
                unplaced,
            )
        session_verdicts = None
        if marks:  # where the episodes start, to know which one each mark is on: a dry run
            starts = _EpisodeStarts()
            _cut_session(session, config, groups, cameras, starts.begin, starts.add, starts.end)
            session_verdicts, early = verdicts(marks, starts.t_ns)
            marks_early += early
        curator.session(session.name, session_verdicts)
        records += _cut_session(
            session, config, groups, cameras, curator.begin, curator.add, curator.end, bar
        )
    if bar is not None:
        bar.close()
    if writer.index == 0:
        if curator.left_out:
            raise ExportError(
                f"no rows to export: every episode was left out ({len(curator.left_out)}: "
                "discarded or marked failed while recording, or in --exclude)"
            )
        raise ExportError(
            "no rows to export: no grasp found (try --episodes session) or the recordings "
            "hold no frames"
        )
    unused = curator.unused()
    for what, numbers in unused.items():
        if numbers:
            log.warning(
                "%s names episode(s) %s, but the recordings gave %d episodes (0..%d): ignored",
                "--exclude" if what == "exclude" else "--task-file",
                ", ".join(map(str, numbers)),
                curator.number,
                curator.number - 1,
            )
    provenance = {
        "exported_by": "deepxpalm export",
        "export_config": dataclasses.asdict(config),
        "features": {f.name: {"unit": f.unit, "frame": f.frame, "what": f.what} for f in features},
        "sessions": [s.metadata for s in sessions],
    }
    info = writer.finish(provenance)
    seconds = time.monotonic() - t_start
    cpu_s = time.process_time() - cpu_start  # what the export itself cost, whatever the load
    # every record of the robot files: the cost's unit (each file is read twice, scan and rows)
    in_files = sum(s.metadata["robot_records"] for s in sessions)
    damage = [
        {"session": s.name, "file": str(s.robot), **d}
        for s in sessions
        for d in s.metadata["damage"]
    ]
    return {
        "out": str(out),
        "sessions": len(sessions),
        "episodes": info["total_episodes"],
        "frames": info["total_frames"],
        "records_read": records,
        "records_in_files": in_files,
        "ms_per_record": round(1000 * seconds / max(in_files, 1), 3),
        "cpu_s": round(cpu_s, 2),
        "cpu_ms_per_record": round(1000 * cpu_s / max(in_files, 1), 3),
        "recorded_s": round(total_s, 1),
        "export_s": round(seconds, 2),
        "peak_rss_mb": round(_peak_rss_mb(), 1),
        "features": [f.name for f in features],
        "damage": damage,
        "cut_short": [s.name for s in sessions if s.metadata["robot_cut_short"]],
        "failed_episodes": curator.failed,
        "left_out": curator.left_out,
        "marks": {
            "read": marks_read,
            "unplaced": marks_unplaced,
            "before_first_episode": marks_early,
        },
        "unused_numbers": unused,
    }


class _EpisodeStarts:
    """A dry run's episode callbacks: the first row time of each episode."""

    def __init__(self) -> None:
        self.t_ns: list[int] = []
        self._open = False

    def begin(self) -> None:
        self._open = True

    def add(self, row: dict[str, Any]) -> None:
        if self._open:
            self.t_ns.append(row["t_ns"])
            self._open = False

    def end(self) -> None:
        self._open = False


def _cut_session(
    session: Any,
    config: Any,
    groups: set[str],
    cameras: tuple[str, ...],
    begin: Any,
    add: Any,
    end: Any,
    bar: Any = None,
) -> int:
    """The session's rows, cut into episodes through ``begin``, ``add``, ``end``.

    The same records give the same episodes, so a dry run (to place the
    operator's marks) and the writing run agree episode by episode. Returns
    the robot records read.
    """
    from deploy.export.resample import EpisodeCutter, SessionResampler
    from deploy.export.session import GAP, camera_records, robot_records

    resampler = SessionResampler(config.fps, session.robot_config, groups, cameras)
    cutter = EpisodeCutter(config, begin, add, end)
    last_t = None
    records = 0
    streams = [robot_records(session), *(camera_records(session, k) for k in cameras)]
    for channel, t_ns, record in heapq.merge(*streams, key=lambda r: r[1]):
        if channel == GAP:  # nothing is known across it: end the episode, start afresh
            cutter.finish()
            resampler = SessionResampler(config.fps, session.robot_config, groups, cameras)
            cutter = EpisodeCutter(config, begin, add, end)
            continue
        records += channel.startswith("robot/")
        for row in resampler.feed(channel, t_ns, record):
            cutter.add(row)
        if bar is not None and resampler.t0 is not None and t_ns - (last_t or 0) > 1e9:
            bar.advance((t_ns - (last_t or resampler.t0)) / 1e9)
            last_t = t_ns
    cutter.finish()
    return records


def _common_cameras(sessions: list[Any]) -> tuple[str, ...]:
    """The cameras every session recorded (a camera some lack is left out, and said so)."""
    keys = set.intersection(*(set(s.cameras) for s in sessions)) if sessions else set()
    for key in set().union(*(s.cameras for s in sessions)) - keys:
        log.warning("only some sessions recorded camera %s: its feature is left out", key)
    return tuple(sorted(keys))


def _numbers(text: str) -> list[int]:
    """``3,7`` -> [3, 7]; argparse reports the error."""
    try:
        numbers = [int(n) for n in text.replace(" ", "").split(",") if n]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not episode numbers like 3,7") from None
    if any(n < 0 for n in numbers):
        raise argparse.ArgumentTypeError("episode numbers are 0 and up")
    return numbers


def _check_out(out: Path) -> None:
    """``--out`` is a new folder or an empty one: an export never mixes its files into others."""
    from deploy.export.session import ExportError

    if out.exists() and not out.is_dir():
        raise ExportError(f"--out {out} is a file; give a new folder for the dataset")
    if out.is_dir() and any(out.iterdir()):
        if (out / "meta" / "info.json").exists():
            raise ExportError(f"{out} already holds a dataset; choose a new --out folder")
        raise ExportError(
            f"--out {out} is not empty and holds no dataset; give a new or empty folder"
        )


def _peak_rss_mb() -> float:
    """This process's peak resident memory so far (Linux reports kB)."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _bar(total_s: float, progress: bool) -> Any:
    """Seconds of recording exported: a bar on a terminal, a line per tenth in a log."""
    if not progress:
        return None
    from common.progress import Progress

    return Progress("export", round(total_s, 1), unit="s recorded")


def run(args: argparse.Namespace) -> int:
    from deploy.export.resample import ExportConfig

    data = load_toml(args.config).get("export", {}) if args.config else {}
    for key in ("fps", "episodes", "task", "exclude", "task_file", "drop_failed"):
        if getattr(args, key) is not None:
            data[key] = getattr(args, key)
    try:
        config = from_dict(ExportConfig, data, where="export")
    except ValueError as e:
        from common.errors import ConfigError

        raise ConfigError(f"export: {e}") from None
    summary = export(args.sessions, args.out, config, progress=not args.no_progress)
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(
            f"{summary['out']}: {summary['episodes']} episodes, {summary['frames']} frames from "
            f"{summary['sessions']} sessions ({summary['recorded_s']} s recorded) in "
            f"{summary['export_s']} s"
        )
        for e in summary["left_out"]:
            why = {"discard": "discarded while recording", "failed": "marked failed"}.get(
                e["reason"], f"--exclude {e['number']}"
            )
            print(f"  left out: an episode of {e.get('rows', 0)} rows of {e['session']} ({why})")
        if summary["failed_episodes"]:
            print(
                "  marked failed (next.success false): episodes "
                + ", ".join(map(str, summary["failed_episodes"]))
            )
        for d in summary["damage"]:
            print(
                f"  damaged: {d['file']} bytes {d['bytes'][0]}..{d['bytes'][1]} unreadable: "
                f"{d['frames_lost']} frames lost, nothing recorded between "
                f"{d['lost_from_s']} s and {d['lost_to_s']} s of the session was exported"
            )
    if summary["damage"] and not args.accept_damage:
        print(
            f"deepxpalm export: {len(summary['damage'])} damaged stretch(es) skipped (exit "
            f"{EXIT_DAMAGED}; --accept-damage to exit 0)",
            file=sys.stderr,
        )
        return EXIT_DAMAGED
    return 0
