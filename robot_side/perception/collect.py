"""Labelled tactile frames, collected the paper's way: every pattern at every grip level.

For each of the twelve patterns the pipette is brought to its tilt and
offset on the pads, either by the arm's wrist (turned about the fingers'
closing axis, shifted along the pad) or by a person presenting it; then the
gripper closes to each grip level in turn, and consecutive frames are kept
with the labels the collection set up. Works on any ``Arm``, ``Gripper`` and
``TactileSensor``: the simulated lab and the real robot alike. Every pose is
checked against the arm's workspace box before the first move.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from common.config.typed import param
from common.errors import ConfigError, DeviceError
from common.tactile.contract import ANGLES_DEG, N_GRIP_LEVELS, N_PATTERNS, classes_of
from common.tactile.synthetic import offset_direction
from robot_side.arm.base import Arm, WorkspaceLimitError
from robot_side.arm.sim.kinematics import matrix_to_rotvec, rotvec_to_matrix
from robot_side.gripper.base import Gripper
from robot_side.perception.dataset import TactileDataset
from robot_side.tactile.base import TactileSensor

log = logging.getLogger(__name__)

POSITION_NAMES = ("centre", "left/up", "right/down")


def _all_patterns() -> list[int]:
    return list(range(N_PATTERNS))


def _all_levels() -> list[int]:
    return list(range(1, N_GRIP_LEVELS + 1))


@dataclass
class CollectConfig:
    patterns: list[int] = param(_all_patterns(), "patterns to collect (3 * angle + position)")
    grip_levels: list[int] = param(_all_levels(), "grip levels to close to, 1..31")
    frames_per_level: int = param(36, "consecutive frames kept per pattern and level (paper: 36)")
    settle_s: float = param(0.25, "wait after the gripper stops before keeping frames")
    grasp_timeout_s: float = param(3.0, "longest wait for the fingers to stop on the pipette")
    frame_timeout_s: float = param(10.0, "longest wait for the next frame before giving up")
    start_angle_deg: float = param(
        90.0, "the pipette's tilt on the pads at the start pose (90: vertical, grasped from above)"
    )
    approach_depth_m: float = param(
        0.025, "the grasp pose lies this far below the start pose (base -z)"
    )
    side_offset_mm: float = param(6.0, "a left/right (up/down) band sits this far off centre")
    release_margin_counts: int = param(
        15, "between levels the fingers open to this far before level 1 (not fully)"
    )
    move_speed_m_s: float = param(0.05, "speed of the collection's moves")
    turn_speed_rad_s: float = param(
        0.1, "speed of the wrist turns (a pure turn's moveL speed; capped like a linear one)"
    )
    session: int = param(0, "written to the data set's sensor column: one id per session")

    def __post_init__(self) -> None:
        if not self.patterns or any(not 0 <= p < N_PATTERNS for p in self.patterns):
            raise ConfigError("collect: patterns must be a non-empty list of 0..11")
        if not self.grip_levels or any(not 1 <= g <= N_GRIP_LEVELS for g in self.grip_levels):
            raise ConfigError("collect: grip_levels must be a non-empty list of 1..31")
        if self.frames_per_level < 1:
            raise ConfigError("collect: frames_per_level must be at least 1")


@dataclass
class Collected:
    frames: list[np.ndarray] = field(default_factory=list)
    pattern: list[int] = field(default_factory=list)
    grip_level: list[int] = field(default_factory=list)
    truth_mismatches: int = 0
    truth_checked: int = 0


def grasp_pose(start: np.ndarray, pattern: int, config: CollectConfig) -> np.ndarray:
    """Where the TCP goes for ``pattern``: turned about the closing axis, shifted along the pad.

    The closing axis is the tool's y; the pad's columns run along tool x and
    its rows along tool z. Turning by ``angle - start_angle`` about tool y
    turns the band on the pads by as much; moving the pad by -d along the
    offset's direction puts the band d off centre.
    """
    angle, position = classes_of(pattern)
    r0 = rotvec_to_matrix(start[3:])
    turn = math.radians(ANGLES_DEG[angle] - config.start_angle_deg)
    r = rotvec_to_matrix(r0 @ np.array([0.0, turn, 0.0])) @ r0
    offset = np.zeros(3)
    if position:
        dx, dy = offset_direction(angle)
        sign = 1.0 if position == 1 else -1.0
        d = sign * config.side_offset_mm / 1000
        offset = -d * (dx * r[:, 0] + dy * r[:, 2])
    pose = np.empty(6)
    pose[:3] = start[:3] + offset - np.array([0.0, 0.0, config.approach_depth_m])
    pose[3:] = matrix_to_rotvec(r)
    return pose


def check_workspace(arm: Arm, poses: list[np.ndarray]) -> None:
    """Refuse the whole collection before the first move if any pose leaves the box."""
    for pose in poses:
        if not arm.limits.contains(pose[:3]):
            raise WorkspaceLimitError(
                f"collection pose {np.round(pose[:3], 4).tolist()} m is outside the workspace "
                f"box {list(arm.limits.workspace_min)}..{list(arm.limits.workspace_max)}: "
                "start nearer the box's centre, reduce approach_depth_m, or widen [arm.limits]"
            )


def collect(
    pads: TactileSensor,
    gripper: Gripper,
    config: CollectConfig,
    arm: Arm | None = None,
    present: Callable[[int], None] | None = None,
    truth: Callable[[], int | None] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> TactileDataset:
    """Collect every (pattern, level) of ``config``.

    With ``arm`` the wrist sets each pattern; otherwise ``present(pattern)``
    must return once a person holds the pipette there. ``truth`` (a
    simulator's ground truth of the pattern on the pads) is checked against
    the label set up, and the disagreements are counted in the data set's meta.
    """
    if arm is None and present is None:
        raise ConfigError("collect: give an arm (the wrist sets the pattern) or a present() prompt")
    start = arm.tcp_pose() if arm is not None else None
    poses = {p: grasp_pose(start, p, config) for p in config.patterns} if arm is not None else {}
    if arm is not None:
        check_workspace(arm, list(poses.values()))
    out = Collected()
    total = len(config.patterns) * len(config.grip_levels)
    done = 0
    t0 = time.monotonic()
    try:
        for pattern in config.patterns:
            gripper.open()
            _wait_open(gripper)
            if arm is not None:
                _go(arm, start, poses[pattern], config)
            else:
                present(pattern)
            for level in config.grip_levels:
                _grasp_at(gripper, level, config)
                frames = _keep_frames(pads, config)
                if truth is not None:
                    seen = truth()
                    out.truth_checked += 1
                    if seen != pattern:
                        out.truth_mismatches += 1
                        log.warning("pattern %d level %d: the world shows %s", pattern, level, seen)
                out.frames.extend(frames)
                out.pattern.extend([pattern] * len(frames))
                out.grip_level.extend([level] * len(frames))
                gripper.move(
                    max(0, gripper.levels.level1_position - config.release_margin_counts),
                    gripper.levels.speed,
                    gripper.levels.level1_force,
                )
                done += 1
                if progress is not None:
                    progress(done, total)
    finally:
        gripper.open()
        if arm is not None and start is not None:
            try:
                _wait_open(gripper)
                _go(arm, start, start, config)
            except DeviceError as e:
                log.warning("collect: could not return to the start pose: %s", e)
    pattern = np.asarray(out.pattern, dtype=np.int64)
    meta: dict[str, Any] = {
        "source": "deepxpalm collect",
        "mode": "wrist" if arm is not None else "presented",
        "session": config.session,
        "frames_per_level": config.frames_per_level,
        "side_offset_mm": config.side_offset_mm,
        "seconds": round(time.monotonic() - t0, 1),
        "truth_checked": out.truth_checked,
        "truth_mismatches": out.truth_mismatches,
    }
    return TactileDataset(
        frames=np.asarray(out.frames, dtype=np.float32).reshape(-1, 2, 10, 10),
        angle=pattern // 3,
        position=pattern % 3,
        grip_level=np.asarray(out.grip_level, dtype=np.int64),
        sensor=np.full(len(pattern), config.session, dtype=np.int64),
        meta=meta,
    )


def _go(arm: Arm, start: np.ndarray, pose: np.ndarray, config: CollectConfig) -> None:
    """Up to the start position, turn there, then down to ``pose``: no turn near the rack."""
    here = arm.tcp_pose()
    up = np.concatenate([start[:3], here[3:]])
    turned = np.concatenate([start[:3], pose[3:]])
    arm.move_to(up, speed=config.move_speed_m_s)
    arm.move_to(turned, speed=config.turn_speed_rad_s)
    arm.move_to(pose, speed=config.move_speed_m_s)


def _wait_open(gripper: Gripper, timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while gripper.position() > 10:
        if time.monotonic() > deadline:
            raise DeviceError(f"gripper did not open in {timeout_s:.0f} s")
        time.sleep(0.02)


def _grasp_at(gripper: Gripper, level: int, config: CollectConfig) -> None:
    gripper.close_to_level(level)
    deadline = time.monotonic() + config.grasp_timeout_s
    while time.monotonic() < deadline:
        st = gripper.state()
        if st.object_status in (1, 2, 3) and st.requested_position == gripper.levels.position(
            level
        ):
            break
        time.sleep(0.01)
    time.sleep(config.settle_s)


def _keep_frames(pads: TactileSensor, config: CollectConfig) -> list[np.ndarray]:
    # the grasp is held still, so a frame late on a loaded machine is still a true one:
    # only a board silent for seconds ends the collection
    sample = pads.latest()
    seq = -1 if sample is None else sample.seq
    frames = []
    for _ in range(config.frames_per_level):
        nxt = pads.wait_for_frame(seq, timeout_s=config.frame_timeout_s)
        if nxt is None:
            raise DeviceError("tactile pads stopped streaming during collection")
        frames.append(np.array(nxt.frame, dtype=np.float32))
        seq = nxt.seq
    return frames
