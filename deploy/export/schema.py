"""The features of an exported dataset: name, dtype, shape, unit and frame.

One table, used by the writer (LeRobot's ``features`` dict in
meta/info.json) and by docs/datasets.md, so the two cannot drift apart.
Frames of reference: ``base`` is the UR3e base frame (metres, rotation
vector in radians, UR's convention); ``common view`` is the tactile pads'
layout in which both fingers are seen from the same side (finger 2
mirrored), as in docs/tactile.md.
"""

from __future__ import annotations

from dataclasses import dataclass

from common.tactile import FRAME_SHAPE


@dataclass(frozen=True)
class Feature:
    name: str
    dtype: str  # LeRobot / datasets dtype: float32, int64
    shape: tuple[int, ...]
    names: list[str] | None
    unit: str
    frame: str
    what: str
    group: str  # "core", "arm" or "gripper": arm/gripper only when every session recorded them

    def info(self) -> dict:
        return {"dtype": self.dtype, "shape": list(self.shape), "names": self.names}


JOINTS = ["shoulder_pan", "shoulder_lift", "elbow", "wrist_1", "wrist_2", "wrist_3"]
POSE = ["x", "y", "z", "rx", "ry", "rz"]
ACTION_NAMES = ["vx", "vy", "vz", "wx", "wy", "wz", "gripper_target"]

FEATURES: list[Feature] = [
    Feature(
        "observation.tactile.frames",
        "float32",
        FRAME_SHAPE,
        ["pad", "row", "col"],
        "N",
        "common view (finger 2 mirrored), pad 0 = finger 1",
        "both pads' 10x10 taxel forces as the robot processed them (sanitised)",
        "core",
    ),
    Feature(
        "observation.tactile.frame_seq",
        "int64",
        (1,),
        None,
        "count",
        "-",
        "sequence number of the held frame (robot/frame.frame_seq)",
        "core",
    ),
    Feature(
        "observation.tactile.age",
        "float32",
        (1,),
        None,
        "s",
        "robot clock",
        "how long before this row's time the held frame was recorded (0 <= age)",
        "core",
    ),
    Feature(
        "observation.stimulus",
        "float32",
        (3, 3),
        ["row", "col"],
        "N",
        "LinkGlide 3x3 cells, as sent to the operator",
        "the last stimulus the robot sent (zeros before the first, or without contact)",
        "core",
    ),
    Feature(
        "observation.perception.pattern",
        "int64",
        (1,),
        None,
        "class",
        "-",
        "recognised pattern 3*angle+position (0..11) of the last stimulus; -1 none",
        "core",
    ),
    Feature(
        "observation.perception.confidence",
        "float32",
        (1,),
        None,
        "probability",
        "-",
        "the classifier's confidence in that pattern; 0 when none",
        "core",
    ),
    Feature(
        "observation.arm.joints",
        "float32",
        (6,),
        JOINTS,
        "rad",
        "joint space",
        "UR3e joint positions (robot/arm, 20 Hz)",
        "arm",
    ),
    Feature(
        "observation.arm.tcp_pose",
        "float32",
        (6,),
        POSE,
        "m, rad",
        "base",
        "TCP pose: position and rotation vector (robot/arm, 20 Hz)",
        "arm",
    ),
    Feature(
        "observation.gripper.position",
        "float32",
        (1,),
        None,
        "counts 0..255",
        "gripper",
        "Robotiq finger position gPO, 0 open .. 255 closed (robot/gripper, 20 Hz)",
        "gripper",
    ),
    Feature(
        "observation.gripper.object_status",
        "int64",
        (1,),
        None,
        "enum",
        "-",
        "Robotiq gOBJ: 0 moving, 1 stopped opening, 2 stopped closing (grasp), 3 at position",
        "gripper",
    ),
    Feature(
        "action",
        "float32",
        (7,),
        ACTION_NAMES,
        "m/s, rad/s, counts 0..255",
        "base",
        "operator commands as the robot applied them: jog velocity after clipping (0 when "
        "stopped or past the jog timeout) and the gripper's target position",
        "core",
    ),
    Feature(
        "annotation.sim_truth_pattern",
        "int64",
        (1,),
        None,
        "class",
        "-",
        "the simulator's true pattern (0..11) of the last stimulus; -1 unknown (real pads). "
        "A label for training, not an observation",
        "core",
    ),
]

#: LeRobot's own per-row columns (its DEFAULT_FEATURES), written for every row
DEFAULT_FEATURES: dict[str, dict] = {
    "timestamp": {"dtype": "float32", "shape": [1], "names": None},
    "frame_index": {"dtype": "int64", "shape": [1], "names": None},
    "episode_index": {"dtype": "int64", "shape": [1], "names": None},
    "index": {"dtype": "int64", "shape": [1], "names": None},
    "task_index": {"dtype": "int64", "shape": [1], "names": None},
}


def features_for(groups: set[str]) -> list[Feature]:
    return [f for f in FEATURES if f.group in groups]
