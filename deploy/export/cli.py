"""``deepxpalm export``: recorded sessions -> one LeRobot dataset (format v3).

Typical uses::

    deepxpalm export runs/today --out datasets/today             # one episode per grasp
    deepxpalm export runs/mon runs/tue --out ds --episodes session --fps 60
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

from common.config import from_dict, load_toml

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
    parser.add_argument("--task", help=f"task string of every episode (default {d.task!r})")
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
    from deploy.export.lerobot_v3 import LeRobotV3Writer
    from deploy.export.resample import EpisodeCutter, ExportConfig, SessionResampler
    from deploy.export.schema import features_for, image_feature
    from deploy.export.session import (
        GAP,
        ExportError,
        camera_records,
        find_sessions,
        robot_records,
        scan,
    )

    config = config or ExportConfig()
    t_start, cpu_start = time.monotonic(), time.process_time()
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
    records = 0
    for session in sessions:
        resampler = SessionResampler(config.fps, session.robot_config, groups, cameras)
        meta_json = json.dumps(session.metadata, sort_keys=True, default=str)
        first_t: list[int] = []

        def begin(session=session, meta_json=meta_json, first_t=first_t) -> None:
            first_t.clear()
            writer.begin_episode(
                config.task,
                {"deepxpalm/session": session.name, "deepxpalm/metadata": meta_json},
            )

        def add(row: dict[str, Any], first_t=first_t) -> None:
            if not first_t:
                first_t.append(row["t_ns"])
                writer.ep["deepxpalm/t_first_ns"] = row["t_ns"]
            writer.add(row)

        cutter = EpisodeCutter(config, begin, add, writer.end_episode)
        last_t = None
        streams = [robot_records(session), *(camera_records(session, k) for k in cameras)]
        for channel, t_ns, record in heapq.merge(*streams, key=lambda r: r[1]):
            if channel == GAP:  # nothing is known across it: end the episode, start afresh
                cutter.finish()
                resampler = SessionResampler(config.fps, session.robot_config, groups, cameras)
                cutter = EpisodeCutter(config, begin, add, writer.end_episode)
                continue
            records += channel.startswith("robot/")
            for row in resampler.feed(channel, t_ns, record):
                cutter.add(row)
            if bar is not None and resampler.t0 is not None and t_ns - (last_t or 0) > 1e9:
                bar.advance((t_ns - (last_t or resampler.t0)) / 1e9)
                last_t = t_ns
        cutter.finish()
    if bar is not None:
        bar.close()
    if writer.index == 0:
        raise ExportError(
            "no rows to export: no grasp found (try --episodes session) or the recordings "
            "hold no frames"
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
    }


def _common_cameras(sessions: list[Any]) -> tuple[str, ...]:
    """The cameras every session recorded (a camera some lack is left out, and said so)."""
    keys = set.intersection(*(set(s.cameras) for s in sessions)) if sessions else set()
    for key in set().union(*(s.cameras for s in sessions)) - keys:
        log.warning("only some sessions recorded camera %s: its feature is left out", key)
    return tuple(sorted(keys))


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
    for key in ("fps", "episodes", "task"):
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
