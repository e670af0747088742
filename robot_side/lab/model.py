"""The lab as an MJCF model: a UR3e, a 2F-85-like gripper with taxel pads, a table, a rack.

Simple geometry, real sizes. The arm's links are mocap bodies placed from the
UR3e's DH chain, and the gripper is a free body welded to a mocap target at
the flange: a teleported mocap body has no velocity, so the pads would slide
over a pipette without friction and could never lift it (the UR simulator owns the joints: the
world shows and checks them, it does not integrate them). The two fingers are
dynamic bodies on slide joints with force-limited position servos, and each
carries a pad of 10 x 10 small box geoms, one per taxel, with soft contact: a
round pipette pressed into the pad touches a band of taxels that widens as
the squeeze grows, which a single rigid pad geom would not show (it gives a
couple of contact points).

Frames: the base frame is the UR's; the table top is z = 0. In the flange
frame the fingers close along y, finger 1 on the -y side; a pad's rows run
along z (row 0 at the fingertip end, +z) and its columns along +x. That is
the common view of the tactile contract: finger 1's side, looking at the
object, "up" towards the fingertips.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from common.tactile.contract import TAXEL_PITCH_MM
from robot_side.arm.sim.kinematics import DH_A, DH_D, HOME_Q, forward, pose_to_matrix
from robot_side.lab.config import LabWorldConfig, PipetteConfig

N_ROWS = N_COLS = 10
PITCH_M = TAXEL_PITCH_MM / 1000  # 24.1 mm / 10: 5.8 cm^2 per pad (the tactile contract)
TAXEL_HALF_M = 0.00118  # a hair under half the pitch: neighbours never touch
TAXEL_DEPTH_HALF_M = 0.00075
PAD_CENTRE_Z_M = 0.15  # the TCP: the fingertip centre, as the UR simulator's tcp_offset
TCP_OFFSET = (0.0, 0.0, PAD_CENTRE_Z_M, 0.0, 0.0, 0.0)
LINK_RADIUS_M = (0.045, 0.04, 0.035, 0.03, 0.03, 0.03)
PALM_HALF_M = (0.03, 0.045, 0.05)  # the gripper's body from the flange to the fingers
PIPETTE_LENGTH_M = 0.12
RACK_HALF_M = (0.12, 0.02, 0.03)


@dataclass(frozen=True)
class PipettePlacement:
    """A pipette in the base frame: its top end, unit axis (bottom to top), radius."""

    top: np.ndarray
    axis: np.ndarray
    radius_m: float


def home_tool() -> np.ndarray:
    """The TCP transform at the UR simulator's home joints."""
    t, _ = forward(np.array(HOME_Q), pose_to_matrix(np.array(TCP_OFFSET)))
    return t


def pipette_placement(config: LabWorldConfig, pipette: PipetteConfig) -> PipettePlacement:
    """Where the rack holds one pipette: its tilt lies in the home grasp plane (tool x-z)."""
    tool = home_tool()
    row_dir = tool[:3, 0].copy()  # tool x at home: along the rack row
    row_dir[2] = 0.0
    row_dir /= np.linalg.norm(row_dir)
    centre = tool[:3, 3].copy()
    centre[:2] += np.asarray(config.rack_centre_m)
    top_z = centre[2] - config.pipette_top_below_tcp_m
    tilt = math.radians(pipette.tilt_deg)
    axis = np.array([0.0, 0.0, math.cos(tilt)]) + row_dir * math.sin(tilt)
    top = np.array([centre[0], centre[1], top_z]) + row_dir * pipette.x_m
    return PipettePlacement(top, axis / np.linalg.norm(axis), pipette.radius_mm / 1000)


def pipette_placements(config: LabWorldConfig) -> list[PipettePlacement]:
    """Where the rack holds each pipette."""
    return [pipette_placement(config, p) for p in config.pipettes]


def axis_quat(axis: np.ndarray) -> np.ndarray:
    """The unit quaternion (w, x, y, z) that turns +z onto ``axis``."""
    z = np.array([0.0, 0.0, 1.0])
    a = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    k = np.cross(z, a)
    s = float(np.linalg.norm(k))
    if s < 1e-12:
        return np.array([1.0, 0.0, 0.0, 0.0]) if a[2] > 0 else np.array([0.0, 1.0, 0.0, 0.0])
    angle = math.atan2(s, float(z @ a))
    return np.array([math.cos(angle / 2), *(math.sin(angle / 2) * k / s)])


def rack_top_z(config: LabWorldConfig) -> float:
    tool = home_tool()
    return float(tool[2, 3] - config.pipette_top_below_tcp_m - 0.07)


def taxel_position(row: int, col: int) -> tuple[float, float]:
    """(x, z) of a taxel's centre in the flange frame, common view (same for both pads)."""
    return ((col - (N_COLS - 1) / 2) * PITCH_M, PAD_CENTRE_Z_M + ((N_ROWS - 1) / 2 - row) * PITCH_M)


def _f(*v: float) -> str:
    return " ".join(f"{x:.6g}" for x in v)


_VISUAL = 'contype="0" conaffinity="0"'


def _link_geoms(j: int) -> str:
    a, d, r = DH_A[j], DH_D[j], LINK_RADIUS_M[j]
    # visual only: the guard checks links against the table geometrically
    parts = [f'<geom type="sphere" size="{r * 1.1:.4f}" rgba=".25 .45 .75 1" {_VISUAL}/>']
    if abs(d) > 1e-6:
        parts.append(
            f'<geom name="link{j}_d" type="capsule" size="{r:.4f}" fromto="{_f(0, 0, 0, 0, 0, d)}" '
            f'rgba=".75 .78 .82 1" {_VISUAL}/>'
        )
    if abs(a) > 1e-6:
        parts.append(
            f'<geom name="link{j}_a" type="capsule" size="{r:.4f}" fromto="{_f(0, 0, d, a, 0, d)}" '
            f'rgba=".75 .78 .82 1" {_VISUAL}/>'
        )
    return "".join(parts)


def _finger(config: LabWorldConfig, k: int) -> str:
    """Finger ``k`` (0 = finger 1 on -y, 1 = finger 2 on +y) with its 100 taxel geoms."""
    side = -1.0 if k == 0 else 1.0
    surface_y = side * config.open_gap_mm / 2000
    taxel_y = surface_y + side * TAXEL_DEPTH_HALF_M
    backing_y = surface_y + side * (2 * TAXEL_DEPTH_HALF_M + 0.004)
    taxels = []
    for row in range(N_ROWS):
        for col in range(N_COLS):
            x, z = taxel_position(row, col)
            taxels.append(
                f'<geom name="taxel{k}_{row}_{col}" type="box" class="taxel" '
                f'pos="{_f(x, taxel_y, z)}"/>'
            )
    return f"""
      <body name="finger{k + 1}" pos="0 0 0" gravcomp="1">
        <joint name="finger{k + 1}" type="slide" axis="{_f(0, -side, 0)}"
               range="0 {config.finger_stroke_mm / 1000:.5f}" damping="80" armature="0.1"/>
        <geom name="finger{k + 1}_body" type="box" size="0.014 0.004 0.04"
              pos="{_f(0, backing_y, 0.125)}" mass="0.08" rgba=".15 .15 .15 1"
              contype="1" conaffinity="1"/>
        {"".join(taxels)}
      </body>"""


def build_mjcf(config: LabWorldConfig) -> str:
    """The whole lab as MJCF text."""
    links = "".join(f'<body name="link{j}" mocap="true">{_link_geoms(j)}</body>' for j in range(6))
    ph = PALM_HALF_M
    gripper = f"""
    <body name="gripper" gravcomp="1">
      <freejoint name="gripper"/>
      <geom name="palm" type="box" size="{_f(*ph)}" pos="0 0 {ph[2]:.4f}" rgba=".2 .2 .22 1"
            mass="{config.gripper_mass_kg}"/>
      <camera name="wrist" pos="0.06 0 0.04" xyaxes="0 1 0 0.88 0 0.48" fovy="70"/>
      {_finger(config, 0)}
      {_finger(config, 1)}
    </body>"""
    pipettes = []
    for i, p in enumerate(pipette_placements(config)):
        # the body's origin is the top end and its z the axis: the rack's hole lets it slide
        # up along its own axis, and re-placing it (a new trial) is one body pose
        pipettes.append(
            f'<body name="pipette{i}" pos="{_f(*p.top)}" quat="{_f(*axis_quat(p.axis))}" '
            f'gravcomp="{1 - config.pipette_weight_kg / config.pipette_mass_kg:.6f}">'
            f'<joint name="pipette{i}" type="slide" axis="0 0 1" '
            f'range="0 {config.pipette_travel_m:.4f}" damping="{config.pipette_damping_n_s_m}"/>'
            f'<geom name="pipette{i}" type="capsule" size="{p.radius_m:.5f}" '
            f'fromto="0 0 {-PIPETTE_LENGTH_M} 0 0 0" mass="{config.pipette_mass_kg}" '
            f'contype="8" conaffinity="4" condim="3" '
            f'friction="{config.pipette_friction} 0.005 0.0001" '
            f'solref="{_f(*config.taxel_solref)}" solimp="{_f(*config.taxel_solimp)}" '
            'rgba=".92 .92 .85 .9"/></body>'
        )
    home = home_tool()[:3, 3]
    rack_c = home.copy()
    rack_c[:2] += np.asarray(config.rack_centre_m)
    rack_c[2] = rack_top_z(config) - RACK_HALF_M[2]
    finger_ctrl = config.finger_stroke_mm / 1000
    return f"""<mujoco model="deepxpalm_lab">
  <option timestep="{config.timestep_s}" integrator="implicitfast" cone="elliptic"
          impratio="{config.friction_impratio}"/>
  <visual><global offwidth="640" offheight="480"/></visual>
  <default>
    <default class="taxel">
      <geom size="{_f(TAXEL_HALF_M, TAXEL_DEPTH_HALF_M, TAXEL_HALF_M)}" mass="0.0002"
            contype="4" conaffinity="12" condim="1" solref="{_f(*config.taxel_solref)}"
            friction="{config.pipette_friction} 0.005 0.0001"
            solimp="{_f(*config.taxel_solimp)}" rgba=".9 .55 .2 1"/>
    </default>
  </default>
  <worldbody>
    <light pos="0 -0.3 1.2" dir="0 0.3 -1" diffuse=".8 .8 .8"/>
    <camera name="overview" pos="{_f(home[0] + 0.55, home[1] - 0.75, home[2] + 0.35)}"
            mode="targetbody" target="gripper"/>
    <geom name="table" type="box" size="0.6 0.6 0.02" pos="0 0 -0.02" rgba=".55 .45 .35 1"
          contype="1" conaffinity="1"/>
    <geom name="rack" type="box" size="{_f(*RACK_HALF_M)}" pos="{_f(*rack_c)}"
          rgba=".3 .5 .3 1" contype="0" conaffinity="0"/>
    {"".join(pipettes)}
    {links}
    <body name="flange_target" mocap="true"/>
    {gripper}
  </worldbody>
  <equality>
    <weld name="wrist" body1="gripper" body2="flange_target"
          solref="{_f(*config.wrist_weld_solref)}"/>
  </equality>
  <actuator>
    <position name="finger1" joint="finger1" kp="{config.finger_kp_n_m}"
              ctrlrange="0 {finger_ctrl:.5f}" forcelimited="true" forcerange="-50 50"/>
    <position name="finger2" joint="finger2" kp="{config.finger_kp_n_m}"
              ctrlrange="0 {finger_ctrl:.5f}" forcelimited="true" forcerange="-50 50"/>
  </actuator>
</mujoco>
"""


def link_poses(q: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
    """Mocap transforms of the six link bodies and the flange, from joint angles."""
    from robot_side.arm.sim.kinematics import dh_transform

    t = np.eye(4)
    links = []
    for j in range(6):
        c, s = math.cos(float(q[j])), math.sin(float(q[j]))
        rz = np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])
        links.append(t @ rz)
        t = t @ dh_transform(float(q[j]), j)
    return links, t
