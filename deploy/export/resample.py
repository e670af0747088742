"""Recorded records -> rows at a fixed rate -> episodes.

Resampling rule (docs/datasets.md): row k of a session stands at time
``t0 + k / fps`` on the robot's clock, where ``t0`` is the first moment
every exported channel has a record. Each observation in the row is the
newest record at or before that time (sample and hold: nothing from the
future leaks into a row); rows end one record period after a camera's last
picture (the video server stopped before the robot). The action is what
the devices were sent at that time: the velocity the arm sent for the last
applied jog (``sent_velocity``) until an ``arm_stop``, another arm
command, the robot's link deadman, or the arm's own jog deadline, which
counts from the operator's send time (``t_sent_ns``), not from when the
robot recorded the command; and the gripper target of the last applied
gripper command. Rejected commands change nothing, as they changed nothing
on the robot.
"""

from __future__ import annotations

import collections
import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from common.config.typed import from_dict, param
from common.tactile.contract import CONTACT_FLOOR_N
from robot_side.arm.base import ArmLimits, clip_jog_velocity
from robot_side.gripper.base import POSITION_OPEN, GripLevels

log = logging.getLogger(__name__)

DEFAULT_CLOSE_LEVEL = 16  # what the robot closes to when a close command names no level
Row = dict[str, Any]


@dataclass
class ExportConfig:
    fps: int = param(30, "rows per second of every episode (LeRobot stores one fps per dataset)")
    episodes: str = param("grasp", "'grasp': one episode per grasp; 'session': one per session")
    task: str = param(
        "grasp the pipette",
        "the task string of episodes given none by a mark or the task file (meta/tasks.parquet)",
    )
    grasp_gap_s: float = param(
        0.3, "contact lost for less than this keeps a grasp going (a slipping finger)"
    )
    min_grasp_s: float = param(0.2, "contact runs shorter than this are brushes, not grasps")
    grasp_margin_s: float = param(
        0.25, "rows kept before a grasp's first and after its last contact (approach, release)"
    )
    video_codec: str = param(
        "libx264",
        "camera features' codec: libx264 (H.264) or libsvtav1 (AV1, LeRobot's own default, "
        "whose encoder deadlocks now and then: docs/datasets.md)",
    )
    exclude: list[int] = param(
        [],
        "episode numbers to leave out, as an export of the same recordings without them "
        "numbers its episodes",
    )
    task_file: Path | None = param(
        None, 'TOML file of NUMBER = "task" lines: each episode\'s task (same numbering)'
    )
    drop_failed: bool = param(
        False, "leave out episodes the operator marked failed (default: kept, success false)"
    )

    def __post_init__(self) -> None:
        if not 1 <= self.fps <= 1000:
            raise ValueError(f"fps must be an integer 1..1000, not {self.fps}")
        if self.episodes not in ("grasp", "session"):
            raise ValueError(f"episodes must be 'grasp' or 'session', not {self.episodes!r}")
        if self.video_codec not in ("libsvtav1", "libx264"):
            raise ValueError(f"video_codec must be libsvtav1 or libx264, not {self.video_codec!r}")
        for name in ("grasp_gap_s", "min_grasp_s", "grasp_margin_s"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must not be negative")
        if any(n < 0 for n in self.exclude):
            raise ValueError("exclude holds episode numbers, 0 and up")


class SessionResampler:
    """Feed records in time order; rows come out at the fixed rate."""

    def __init__(
        self,
        fps: int,
        robot_config: dict[str, Any],
        groups: set[str],
        cameras: tuple[str, ...] = (),
    ) -> None:
        self.period_ns = 1e9 / fps
        self.groups = groups
        #: camera key -> the held picture's JPEG bytes (channel ``camera/<key>``)
        self.cameras = cameras
        self.images: dict[str, bytes] = {}
        self.ended = False  # a camera stopped: rows would hold its last picture for ever
        arm = robot_config.get("arm", {})
        self.arm_limits = from_dict(ArmLimits, arm.get("limits", {}), where="robot.arm.limits")
        gripper = robot_config.get("gripper", {})
        self.levels = from_dict(GripLevels, gripper.get("levels", {}), where="robot.gripper.levels")
        render = robot_config.get("render", {})
        self.contact_threshold_n = float(render.get("contact_threshold_n", CONTACT_FLOOR_N))
        self.t0: int | None = None
        self.k = 0
        self._held: list[Row] = []  # rows not yet followed by a tactile frame
        # held observations
        self.frame: np.ndarray | None = None
        self.frame_seq = -1
        self.frame_t = 0
        self.stimulus = np.zeros((3, 3), np.float32)
        self.pattern = -1
        self.confidence = 0.0
        self.truth = -1
        self.joints: np.ndarray | None = None
        self.pose: np.ndarray | None = None
        self.gripper_position: float | None = None
        self.object_status = 0
        # command state
        self.jog = np.zeros(6)
        self.jog_until = 0
        self.grip_target: float | None = None

    def feed(self, channel: str, t_ns: int, record: dict[str, Any]) -> Iterator[Row]:
        """Rows due before ``t_ns``, then the record is applied.

        Rows wait until a later tactile frame shows the pads' stream went on past them:
        the session's rows end at its last frame, not at the last record of any channel
        (a gripper or arm still recorded while the node shut its devices down would
        otherwise add rows whose frame nobody knows still held).
        """
        if self.t0 is not None:
            self._held.extend(self._rows_before(t_ns))
        self._apply(channel, t_ns, record)
        if self.t0 is None and self._ready():
            self.t0 = t_ns
        if channel == "robot/frame" and self._held:
            held, self._held = self._held, []
            yield from held

    def _ready(self) -> bool:
        if self.frame is None or len(self.images) < len(self.cameras):
            return False
        if "arm" in self.groups and self.joints is None:
            return False
        return not ("gripper" in self.groups and self.gripper_position is None)

    def _rows_before(self, t_ns: int) -> Iterator[Row]:
        while not self.ended:
            t_k = self.t0 + round(self.k * self.period_ns)
            if t_k >= t_ns:
                return
            yield self._row(t_k)
            self.k += 1

    def _row(self, t_k: int) -> Row:
        jog = self.jog if t_k < self.jog_until else np.zeros(6)
        target = POSITION_OPEN if self.grip_target is None else self.grip_target
        row: Row = {
            "t_ns": t_k,
            "contact": bool(self.frame.max() >= self.contact_threshold_n),
            "observation.tactile.frames": self.frame,
            "observation.tactile.frame_seq": self.frame_seq,
            "observation.tactile.age": (t_k - self.frame_t) / 1e9,
            "observation.stimulus": self.stimulus,
            "observation.perception.pattern": self.pattern,
            "observation.perception.confidence": self.confidence,
            "action": np.concatenate([jog, [target]]).astype(np.float32),
            "annotation.sim_truth_pattern": self.truth,
        }
        if "arm" in self.groups:
            row["observation.arm.joints"] = self.joints
        if "gripper" in self.groups:
            row["observation.gripper.object_status"] = self.object_status
        if "state" in self.groups:
            row["observation.state"] = np.append(self.pose, self.gripper_position)
        for key in self.cameras:
            row[f"observation.images.{key}"] = self.images[key]
        return row

    def _apply(self, channel: str, t_ns: int, r: dict[str, Any]) -> None:
        if channel == "robot/frame":
            self.frame = np.asarray(r["frame"], np.float32)
            self.frame_seq = int(r["frame_seq"])
            self.frame_t = t_ns
        elif channel == "robot/stimulus":
            d = r.get("decoded") or {}
            if "stimulus" not in d:
                return  # a wire that did not decode: the operator got nothing from it either
            self.stimulus = np.asarray(d["stimulus"], np.float32).reshape(3, 3)
            self.pattern = -1 if d.get("pattern") is None else int(d["pattern"])
            self.confidence = 0.0 if d.get("confidence") is None else float(d["confidence"])
            truth = d.get("sim_truth_pattern")
            self.truth = -1 if truth is None else int(truth)
        elif channel == "robot/arm":
            self.joints = np.asarray(r["joints"], np.float64)
            self.pose = np.asarray(r["tcp_pose"], np.float64)
        elif channel == "robot/gripper":
            self.gripper_position = float(r["position"])
            self.object_status = int(r["object_status"])
            if self.grip_target is None:
                self.grip_target = float(r["requested_position"])
        elif channel == "robot/command" and r.get("outcome") == "applied":
            self._command(t_ns, r)
        elif channel.startswith("camera/"):
            self.images[channel.removeprefix("camera/")] = r["data"]
        elif channel.startswith("camera-end/"):
            self.ended = True
        elif channel == "robot/link" and r.get("state") == "down":
            self._stop_jog()  # the link deadman stopped the arm (at or before this heartbeat)

    def _command(self, t_ns: int, r: dict[str, Any]) -> None:
        action = r.get("action", "")
        if action == "gripper_open":
            self.grip_target = float(POSITION_OPEN)
        elif action == "gripper_close":
            level = r.get("grip_level") or DEFAULT_CLOSE_LEVEL
            self.grip_target = float(self.levels.position(level))
        elif action == "gripper_hold":
            if self.gripper_position is not None:
                self.grip_target = self.gripper_position
        elif action == "gripper_ease":  # as Gripper.ease: just past level 1, never closing
            here = self.gripper_position if self.gripper_position is not None else POSITION_OPEN
            self.grip_target = float(min(here, self.levels.ease_position()))
        elif action == "arm_jog" and r.get("velocity"):
            sent = r.get("sent_velocity")
            if sent is not None:
                self.jog = np.asarray(sent, np.float64)
            else:  # recorded before sent_velocity was: clip as the arm clips
                self.jog = clip_jog_velocity(self.arm_limits, r["velocity"], self.pose)
            t_sent = r.get("t_sent_ns")
            start = t_ns if t_sent is None else min(int(t_sent), t_ns)
            self.jog_until = start + round(self.arm_limits.jog_timeout_s * 1e9)
        elif action.startswith("arm"):
            self._stop_jog()

    def _stop_jog(self) -> None:
        self.jog = np.zeros(6)
        self.jog_until = 0


class EpisodeCutter:
    """Rows in, episodes out: the whole session, or one episode per grasp.

    A grasp is a run of rows in contact (the largest taxel at or above the
    session's contact threshold), runs closer than ``grasp_gap_s`` merged,
    runs shorter than ``min_grasp_s`` dropped, ``grasp_margin_s`` of rows
    kept on each side. Memory: at most gap + margin rows are held.
    """

    def __init__(
        self,
        config: ExportConfig,
        begin: Callable[[], None],
        add: Callable[[Row], None],
        end: Callable[[], None],
    ) -> None:
        self.per_session = config.episodes == "session"
        fps = config.fps
        self.gap = max(1, round(config.grasp_gap_s * fps))
        self.min_rows = max(1, round(config.min_grasp_s * fps))
        self.margin = round(config.grasp_margin_s * fps)
        self._begin, self._add, self._end = begin, add, end
        self.pre: collections.deque[Row] = collections.deque(maxlen=max(self.margin, 1))
        self.episode: list[Row] | None = None  # rows of a grasp not yet long enough to keep
        self.open = False  # an episode has been begun in the writer
        self.contact_rows = 0
        self.tail: list[Row] = []  # rows since the last contact

    def add(self, row: Row) -> None:
        if self.per_session:
            if not self.open:
                self._begin()
                self.open = True
            self._add(row)
            return
        if self.episode is None:
            if row["contact"]:
                self.episode = [*(list(self.pre) if self.margin else []), row]
                self.pre.clear()
                self.contact_rows = 1
                self.tail = []
            elif self.margin:
                self.pre.append(row)
            return
        if row["contact"]:
            for r in self.tail:
                self._keep(r)
            self.tail = []
            self.contact_rows += 1
            self._keep(row)
            return
        self.tail.append(row)
        if len(self.tail) >= self.gap:
            self._close()

    def _keep(self, row: Row) -> None:
        if self.open:
            self._add(row)
            return
        self.episode.append(row)
        if self.contact_rows >= self.min_rows:  # long enough: hand it to the writer
            self._begin()
            self.open = True
            for r in self.episode:
                self._add(r)
            self.episode = []

    def _close(self) -> None:
        keep, rest = self.tail[: self.margin], self.tail[self.margin :]
        if self.open:
            for r in keep:
                self._add(r)
            self._end()
        self.open = False
        self.episode = None
        self.tail = []
        self.pre.clear()
        if self.margin:
            self.pre.extend(rest[-self.margin :])

    def finish(self) -> None:
        if self.per_session:
            if self.open:
                self._end()
            self.open = False
            return
        if self.episode is not None:
            self._close()
