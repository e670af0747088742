"""One recorded session: its files, its metadata, its records in time order.

A session is a folder as ``deepxpalm demo --record DIR`` writes it
(``robot.mcap``, and ``operator.mcap`` when the operator recorded too), or
a single robot recording. The dataset is built on the robot's clock: every
observation and every applied command is a robot record. The operator's
recording only adds metadata (latency, loss, clock offset, calibration).
"""

from __future__ import annotations

import hashlib
import heapq
import json
import logging
import statistics
import tomllib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from common.errors import ConfigError
from common.recording.mcap_recorder import Damage, RecordingReader

log = logging.getLogger(__name__)

#: how far out of time order the recorder may write records: a record's
#: time is taken before it is queued, and the queue is written in order, so
#: the disorder is one node loop iteration; 1 s is a wide margin
REORDER_WINDOW_NS = 1_000_000_000
ROBOT_CHANNELS = (
    "robot/frame",
    "robot/stimulus",
    "robot/command",
    "robot/arm",
    "robot/gripper",
    "robot/link",  # its state: the link deadman stops a jog
)


class ExportError(ConfigError):
    """A recording cannot be exported; the message names the file and the fix."""


@dataclass
class Session:
    name: str
    robot: Path
    operator: Path | None = None
    metadata: dict[str, Any] = field(default_factory=dict)
    channels: set[str] = field(default_factory=set)
    robot_config: dict[str, Any] = field(default_factory=dict)
    #: the video server's recordings in the folder (camera*.mcap), and after ``scan``
    #: camera key -> (its files, (width, height) of its first picture, record period in ns)
    camera_files: list[Path] = field(default_factory=list)
    cameras: dict[str, tuple[list[Path], tuple[int, int], int]] = field(default_factory=dict)


def find_sessions(paths: list[Path]) -> list[Session]:
    """Each path is a session folder, a folder of session folders, or a robot .mcap."""
    out: list[Session] = []
    for path in paths:
        if path.is_file():
            out.append(Session(path.stem, path))
        elif (path / "robot.mcap").is_file():
            op = path / "operator.mcap"
            session = Session(path.name, path / "robot.mcap", op if op.is_file() else None)
            session.camera_files = sorted(path.glob("camera*.mcap"))
            out.append(session)
        elif path.is_dir():
            subs = sorted(p for p in path.iterdir() if (p / "robot.mcap").is_file())
            if not subs:
                raise ExportError(f"{path} holds no robot.mcap and no session folder with one")
            out.extend(find_sessions(subs))
        else:
            raise ExportError(f"{path} does not exist")
    return out


#: the channel of the marker ``robot_records`` yields where a damaged stretch was skipped
GAP = "export/gap"
#: the marker ``camera_records`` yields one record period after a camera's last picture
#: (``camera-end/<key>``): no row after it, as none before the first picture
CAMERA_END = "camera-end/"


def robot_records(session: Session) -> Iterator[tuple[str, int, dict[str, Any]]]:
    """The session's robot records that make a dataset, in time order (bounded memory).

    The recorder writes records in queue order, which is time order up to
    one loop iteration; a heap holding ``REORDER_WINDOW_NS`` of records
    restores the order exactly. Where the reader skipped a damaged stretch,
    everything before it comes out first, then a ``GAP`` marker: nothing
    recorded in the stretch is known, so no row may hold a value across it.
    """
    heap: list[tuple[int, int, str, dict[str, Any]]] = []
    n = 0
    reader = RecordingReader(session.robot)
    damages = 0
    for channel, t_ns, record in reader:
        if len(reader.damage) != damages:
            damages = len(reader.damage)
            while heap:
                t, _, ch, rec = heapq.heappop(heap)
                yield ch, t, rec
            yield GAP, t_ns, {"damage": reader.damage[-1]}
        if channel not in ROBOT_CHANNELS:
            continue
        n += 1
        heapq.heappush(heap, (t_ns, n, channel, record))
        while heap and heap[0][0] < t_ns - REORDER_WINDOW_NS:
            t, _, ch, rec = heapq.heappop(heap)
            yield ch, t, rec
    while heap:
        t, _, ch, rec = heapq.heappop(heap)
        yield ch, t, rec
    if reader.truncated:
        log.warning("%s was cut short (%s): exported up to the cut", session.robot, reader.error)


def camera_records(session: Session, key: str) -> Iterator[tuple[str, int, dict[str, Any]]]:
    """The pictures of camera ``key`` in time order, as channel ``camera/<key>``.

    A restarted video server's file (``camera.restart1.mcap``) follows the
    first: each file is in time order, and the files are merged.
    """
    from robot_side.video.camera_recording import CHANNEL

    def one(path: Path) -> Iterator[tuple[str, int, dict[str, Any]]]:
        reader = RecordingReader(path)
        for channel, t_ns, record in reader:
            if channel == CHANNEL:
                yield f"camera/{key}", t_ns, record
        if reader.damage:
            log.warning("%s: %d damaged stretch(es) skipped", path, len(reader.damage))

    last = None
    for item in heapq.merge(*(one(p) for p in session.cameras[key][0]), key=lambda r: r[1]):
        last = item[1]
        yield item
    if last is not None:  # the last picture stands for one period, then the camera is gone
        yield f"{CAMERA_END}{key}", last + session.cameras[key][2], {}


def _scan_cameras(session: Session) -> None:
    """Which cameras the session's camera files hold, and each one's picture size."""
    from robot_side.video.camera_recording import CHANNEL

    for path in session.camera_files:
        reader = RecordingReader(path)
        size = None
        for channel, _, record in reader:
            if channel == CHANNEL:
                size = (int(record["width"]), int(record["height"]))
                break
        camera = reader.metadata.get("deepxpalm.camera", {})
        key = camera.get("camera")
        if key is None or size is None:
            log.warning("%s holds no camera pictures: left out", path)
            continue
        period_ns = round(1e9 / float(camera.get("record_fps", 10)))
        files, first, _ = session.cameras.get(key, ([], size, period_ns))
        session.cameras[key] = ([*files, path], first, period_ns)


def scan(session: Session) -> Session:
    """Read the session's metadata: one pass over each file, keeping only summaries."""
    robot_reader = RecordingReader(session.robot)
    channels: set[str] = set()
    first_frame_ns = last_ns = None
    robot_link: dict[str, Any] = {}
    n_records = 0
    for channel, t_ns, record in robot_reader:
        n_records += 1
        channels.add(channel)
        if channel == "robot/frame" and first_frame_ns is None:
            first_frame_ns = t_ns
        if channel == "robot/link":
            robot_link = record
        last_ns = t_ns
    if last_ns is None and robot_reader.truncated:
        raise ExportError(
            f"{session.robot} holds no records: it is empty ({session.robot.stat().st_size} "
            "bytes) or was cut before its first chunk"
        )
    node = robot_reader.metadata.get("deepxpalm.node", {})
    if node.get("node", "robot") != "robot":
        raise ExportError(
            f"{session.robot} is a {node.get('node')} recording; export needs the robot's "
            "(robot.mcap: it holds the frames and the applied commands)"
        )
    if "robot/frame" not in channels:
        raise ExportError(f"{session.robot} holds no tactile frames (robot/frame)")
    config = _toml(node.get("config_toml"), session.robot).get("robot", {})
    session.robot_config = config
    session.channels = channels
    meta: dict[str, Any] = {
        "session": session.name,
        "robot_recording": str(session.robot),
        "robot_records": n_records,
        "robot_closed_cleanly": robot_reader.complete,
        "robot_cut_short": robot_reader.truncated,
        "damage": [_damage_summary(d, first_frame_ns) for d in robot_reader.damage],
        "duration_s": round((last_ns - first_frame_ns) / 1e9, 3) if last_ns else 0.0,
        "render_mode": config.get("render", {}).get("mode"),
        "model": _model_version(config.get("classifier", {})),
        "tactile": config.get("tactile", {}),
        "robot_link_at_end": _numbers(robot_link),
    }
    session_meta = robot_reader.metadata.get("deepxpalm.session", {})
    if session.operator is not None:
        meta.update(_operator_summary(session.operator))
        session_meta = session_meta or meta.pop("_session_meta", {})
    meta.pop("_session_meta", None)
    meta["scene"] = session_meta.get("scene")
    meta["network_scenario"] = session_meta.get("network_scenario")
    _scan_cameras(session)
    meta["cameras"] = {
        key: {"files": [str(p) for p in files], "width": size[0], "height": size[1]}
        for key, (files, size, _) in session.cameras.items()
    }
    session.metadata = meta
    return session


def _damage_summary(d: Damage, t0_ns: int | None) -> dict[str, Any]:
    """A skipped stretch as the export reports it: seconds from the session's first frame."""

    def s(t: int | None) -> float | None:
        return None if t is None or t0_ns is None else round((t - t0_ns) / 1e9, 3)

    return {
        "bytes": [d.byte_start, d.byte_end],
        "lost_from_s": s(d.t_before_ns),
        "lost_to_s": s(d.t_after_ns),
        "lost_from_ns": d.t_before_ns,
        "lost_to_ns": d.t_after_ns,
        "frames_lost": d.records_lost.get("robot/frame", 0),
        "records_lost": dict(d.records_lost),
        "error": d.error,
    }


def _operator_summary(path: Path) -> dict[str, Any]:
    reader = RecordingReader(path)
    offsets: list[int] = []
    last_link: dict[str, Any] = {}
    for channel, _, record in reader:
        if channel == "operator/link":
            last_link = record
            if record.get("clock_offset_ns") is not None:
                offsets.append(int(record["clock_offset_ns"]))
    node = reader.metadata.get("deepxpalm.node", {})
    config = _toml(node.get("config_toml"), path).get("operator", {})
    link = _numbers(last_link)
    return {
        "operator_recording": str(path),
        "clock_offset_ns_median": int(statistics.median(offsets)) if offsets else None,
        "clock_offset_ns_spread": (max(offsets) - min(offsets)) if offsets else None,
        "latency_ms": {k: v for k, v in link.items() if k.startswith("latency_")},
        "link": {k: v for k, v in link.items() if k.startswith("link_")},
        "calibration": config.get("servos", {}).get("calibration")
        or config.get("servos", {}).get("calibration_file"),
        "_session_meta": reader.metadata.get("deepxpalm.session", {}),
    }


def _numbers(record: dict[str, Any]) -> dict[str, float]:
    return {k: v for k, v in record.items() if isinstance(v, (int, float)) and v is not None}


def _toml(text: str | None, where: Path) -> dict[str, Any]:
    if not text:
        log.warning("%s holds no config; exporting with today's defaults", where)
        return {}
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ExportError(f"the config stored in {where} does not parse: {e}") from None


def _model_version(classifier: dict[str, Any]) -> dict[str, Any]:
    """Which model the session ran: its configured path and, when here, the file's sha256."""
    from robot_side.perception.weights import DEFAULT_MODEL

    path = Path(classifier["path"]) if classifier.get("path") else DEFAULT_MODEL
    out: dict[str, Any] = {
        "path": str(path),
        "shipped_default": not classifier.get("path"),
        "backend": classifier.get("backend"),
    }
    if path.is_file():
        out["sha256_on_exporting_machine"] = hashlib.sha256(path.read_bytes()).hexdigest()
    return out


def dumps(meta: dict[str, Any]) -> str:
    return json.dumps(meta, sort_keys=True, default=str)
