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

from common.tactile.contract import FRAME_SHAPE


@dataclass(frozen=True)
class Feature:
    name: str
    dtype: str  # LeRobot / datasets dtype: float32, int64, bool
    shape: tuple[int, ...]
    names: list[str] | None
    unit: str
    frame: str
    what: str
    #: "core"; "arm", "gripper": only when every session recorded robot/arm, robot/gripper;
    #: "state": only when every session recorded both
    group: str
    #: a video feature's ``info`` (codec, fps, ...), filled by the writer; None otherwise
    video_info: dict | None = None

    def info(self) -> dict:
        out = {"dtype": self.dtype, "shape": list(self.shape), "names": self.names}
        if self.video_info is not None:
            out["info"] = self.video_info
        return out


JOINTS = ["shoulder_pan", "shoulder_lift", "elbow", "wrist_1", "wrist_2", "wrist_3"]
#: LeRobot's names for an end effector (``ee.x`` .. ``ee.wz``, its kinematic processors)
#: and for a position-controlled motor (``gripper.pos``)
STATE_NAMES = ["ee.x", "ee.y", "ee.z", "ee.wx", "ee.wy", "ee.wz", "gripper.pos"]
ACTION_NAMES = ["ee.vx", "ee.vy", "ee.vz", "ee.vwx", "ee.vwy", "ee.vwz", "gripper.pos"]

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
        "observation.state",
        "float32",
        (7,),
        STATE_NAMES,
        "m, rad, counts 0..255",
        "base",
        "the policy's state (LeRobot looks it up by this name): the TCP pose, position and "
        "rotation vector (robot/arm), then the Robotiq finger position gPO, 0 open .. 255 "
        "closed (robot/gripper); both 20 Hz",
        "state",
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
        "what the arm and gripper were sent: the jog velocity the arm sent (robot/command "
        "sent_velocity), 0 once stopped or past the arm's jog deadline (the operator's send "
        "time plus jog_timeout_s); and the gripper's target finger position",
        "core",
    ),
    Feature(
        "next.success",
        "bool",
        (1,),
        None,
        "true/false",
        "-",
        "LeRobot's success flag: true on the last row of an episode that succeeded (not marked "
        "failed by the operator), false on every other row; the episode's metadata says the "
        "same (deepxpalm/success)",
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


def image_feature(camera: str, width: int, height: int) -> Feature:
    """A camera's pictures, as LeRobot names them (``observation.images.<camera>``)."""
    return Feature(
        f"observation.images.{camera}",
        "video",
        (height, width, 3),
        ["height", "width", "channels"],
        "RGB 0..255 (LeRobot's loader: 0..1, channels first)",
        f"the {camera} camera (robot PC, camera.mcap)",
        "the newest camera picture at or before the row's time (recorded at the video "
        "server's record_fps, held over the rows between pictures)",
        "images",
    )
