"""A kinematic UR3e: the TCP moves as the commands say, the joints follow.

No dynamics, no collisions: the pose integrates the commanded motion
exactly (straight lines for moveL, ramped velocities for speedL, a
time-constant chase for servoL, decelerations for stops), and the joints
track it with one damped least-squares IK step per tick on the UR3e's
published DH parameters, so ``actual_q`` and ``actual_TCP_pose`` agree the
way they do on the robot.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field

import numpy as np

from common.rotation import matrix_to_rotvec, rotvec_to_matrix

# UR3e DH parameters (Universal Robots' published values), metres and radians.
DH_A = (0.0, -0.24355, -0.2132, 0.0, 0.0, 0.0)
DH_D = (0.15185, 0.0, 0.0, 0.13105, 0.08535, 0.0921)
DH_ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)

#: Shoulder up, elbow up, tool pointing down: the usual UR home.
HOME_Q = (0.0, -math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, 0.0)

MAX_TCP_SPEED_M_S = 1.0  # UR3e tool speed limit
MAX_TCP_ROT_SPEED_RAD_S = math.pi


_YZX = [1, 2, 0]
_ZXY = [2, 0, 1]


def dh_transform(theta: float, i: int) -> np.ndarray:
    """Joint ``i``'s Denavit-Hartenberg transform at angle ``theta``."""
    ct, st = math.cos(theta), math.sin(theta)
    ca, sa = math.cos(DH_ALPHA[i]), math.sin(DH_ALPHA[i])
    return np.array(
        [
            [ct, -st * ca, st * sa, DH_A[i] * ct],
            [st, ct * ca, -ct * sa, DH_A[i] * st],
            [0.0, sa, ca, DH_D[i]],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


def pose_to_matrix(pose: np.ndarray) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = rotvec_to_matrix(np.asarray(pose[3:], dtype=float))
    t[:3, 3] = pose[:3]
    return t


def matrix_to_pose(t: np.ndarray) -> np.ndarray:
    return np.concatenate([t[:3, 3], matrix_to_rotvec(t[:3, :3])])


def forward(q: np.ndarray, tcp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """TCP transform and the 6x6 geometric Jacobian at joint angles ``q``."""
    z = np.empty((6, 3))
    o = np.empty((6, 3))
    t = np.eye(4)
    for i in range(6):
        z[i] = t[:3, 2]
        o[i] = t[:3, 3]
        t = t @ dh_transform(float(q[i]), i)
    t_tcp = t @ tcp
    jac = np.empty((6, 6))
    r = t_tcp[:3, 3] - o  # np.cross costs ~60 us here; the explicit form ~5 us
    jac[:3] = (z[:, _YZX] * r[:, _ZXY] - z[:, _ZXY] * r[:, _YZX]).T
    jac[3:] = z.T
    return t_tcp, jac


def rotation_error(target: np.ndarray, current: np.ndarray) -> np.ndarray:
    """Rotation vector (base frame) that turns ``current`` into ``target``."""
    return matrix_to_rotvec(target @ current.T)


class Mode(enum.Enum):
    IDLE = "idle"
    MOVE_L = "moveL"
    MOVE_J = "moveJ"
    SPEED_L = "speedL"
    SERVO_L = "servoL"
    STOPPING = "stopping"


@dataclass
class _Move:
    start: np.ndarray  # pose at start
    target: np.ndarray
    length: float  # path parameter length (m, or rad for pure rotations)
    speed: float
    accel: float
    s: float = 0.0  # travelled along the path
    sd: float = 0.0  # path speed

    def __post_init__(self) -> None:
        self.r0 = rotvec_to_matrix(self.start[3:])
        self.r1 = rotvec_to_matrix(self.target[3:])
        self.turn = matrix_to_rotvec(self.r1 @ self.r0.T)  # base-frame rotation start -> target


#: Joint tracking stops once the joints put the TCP this close to its pose (m and rad
#: combined): 0.1 um, whose pay-off on the next tick is below 1e-3 rad/s even at 0.1 ms.
JOINT_TRACK_TOLERANCE = 1e-7
#: and after this many steps, converged or not (a pose out of reach, near a singularity)
JOINT_TRACK_MAX_STEPS = 8


@dataclass
class KinematicArm:
    """The arm state the simulator advances every tick (not thread-safe: the server locks)."""

    tcp_offset: np.ndarray = field(default_factory=lambda: np.array([0, 0, 0.15, 0, 0, 0.0]))
    q: np.ndarray = field(default_factory=lambda: np.array(HOME_Q, dtype=float))

    def __post_init__(self) -> None:
        self.tcp = pose_to_matrix(self.tcp_offset)
        t, _ = forward(self.q, self.tcp)
        self.pose = matrix_to_pose(t)
        self.rot = t[:3, :3].copy()
        self.pos = t[:3, 3].copy()
        self.velocity = np.zeros(6)  # TCP twist, base frame
        self.qd = np.zeros(6)
        self.mode = Mode.IDLE
        self.target_velocity = np.zeros(6)
        self.accel = 1.0
        self.move: _Move | None = None
        self.servo_target: np.ndarray | None = None
        self.servo_time = 0.008
        self._joint_move: tuple[np.ndarray, np.ndarray, float, float] | None = None
        self._joints_settled = False
        self._rotvec_of: tuple[bytes, np.ndarray] = (b"", np.zeros(3))  # (rot's bytes, rotvec)

    # -- commands ------------------------------------------------------------

    def move_l(self, target: np.ndarray, speed: float, accel: float) -> None:
        start = self.current_pose()
        dp = float(np.linalg.norm(target[:3] - start[:3]))
        dr = float(np.linalg.norm(rotation_error(rotvec_to_matrix(target[3:]), self.rot)))
        length = dp if dp > 1e-6 else dr
        self.move = _Move(start, np.array(target, dtype=float), length, speed, accel)
        self.mode = Mode.MOVE_L if length > 1e-9 else Mode.IDLE

    def move_j(self, q_target: np.ndarray, speed: float, accel: float) -> None:
        self._joint_move = (self.q.copy(), np.array(q_target, dtype=float), speed, accel)
        self._mj_s, self._mj_sd = 0.0, 0.0
        self.mode = Mode.MOVE_J

    def speed_l(self, xd: np.ndarray, accel: float) -> None:
        self.target_velocity = np.array(xd, dtype=float)
        self.accel = max(accel, 1e-3)
        self.mode = Mode.SPEED_L

    def servo_l(self, target: np.ndarray, time_s: float, lookahead_s: float) -> None:
        self.servo_target = np.array(target, dtype=float)
        self.servo_time = max(time_s, lookahead_s, 0.002)
        self.mode = Mode.SERVO_L

    def stop(self, decel: float) -> None:
        if self.mode == Mode.IDLE:
            return
        self.target_velocity = np.zeros(6)
        self.accel = max(decel, 1e-3)
        self.mode = Mode.STOPPING
        self.move = None
        self.servo_target = None
        self._joint_move = None

    @property
    def moving(self) -> bool:
        return self.mode != Mode.IDLE

    def current_pose(self) -> np.ndarray:
        """The TCP pose; a still arm's rotation vector is converted once, not every package."""
        key = self.rot.tobytes()
        if key != self._rotvec_of[0]:
            self._rotvec_of = (key, matrix_to_rotvec(self.rot))
        return np.concatenate([self.pos, self._rotvec_of[1]])

    # -- integration ---------------------------------------------------------

    def step(self, dt: float) -> None:
        if self.mode == Mode.MOVE_J:
            self._step_move_j(dt)
            return
        if self.mode == Mode.MOVE_L:
            self._step_move_l(dt)
        elif self.mode in (Mode.SPEED_L, Mode.STOPPING):
            # URScript's speedl(xd, a) and stopl(a): the translation ramps at a in m/s^2 and
            # the turn at aRot in rad/s^2, each on its own (aRot defaults to a)
            max_dv = self.accel * dt
            self.velocity = np.concatenate(
                [
                    _approach(self.velocity[:3], self.target_velocity[:3], max_dv),
                    _approach(self.velocity[3:], self.target_velocity[3:], max_dv),
                ]
            )
            self._integrate(self.velocity, dt)
            if self.mode == Mode.STOPPING and not np.any(self.velocity):
                self.mode = Mode.IDLE
        elif self.mode == Mode.SERVO_L and self.servo_target is not None:
            err = np.concatenate(
                [
                    self.servo_target[:3] - self.pos,
                    rotation_error(rotvec_to_matrix(self.servo_target[3:]), self.rot),
                ]
            )
            v = err / self.servo_time
            v[:3] = _cap(v[:3], MAX_TCP_SPEED_M_S)
            v[3:] = _cap(v[3:], MAX_TCP_ROT_SPEED_RAD_S)
            self.velocity = v
            self._integrate(v, dt)
        else:
            self.velocity = np.zeros(6)
        self._track_joints(dt)

    def _step_move_l(self, dt: float) -> None:
        m = self.move
        assert m is not None
        remaining = m.length - m.s
        # decelerate when the stopping distance reaches what is left
        if m.sd * m.sd / (2 * m.accel) >= remaining:
            m.sd = max(0.0, m.sd - m.accel * dt)
        else:
            m.sd = min(m.speed, m.sd + m.accel * dt)
        old_frac = m.s / m.length
        m.s = min(m.length, m.s + max(m.sd, 1e-4 if remaining > 0 else 0.0) * dt)
        frac = m.s / m.length
        old_pos = self.pos.copy()
        self.pos = m.start[:3] + frac * (m.target[:3] - m.start[:3])
        self.rot = rotvec_to_matrix(frac * m.turn) @ m.r0
        self.velocity = np.concatenate(
            [(self.pos - old_pos) / dt, m.turn * ((frac - old_frac) / dt)]
        )
        if m.s >= m.length - 1e-12:
            self.pos, self.rot = m.target[:3].copy(), m.r1
            self.velocity = np.zeros(6)
            self.mode = Mode.IDLE
            self.move = None

    def _step_move_j(self, dt: float) -> None:
        assert self._joint_move is not None
        q0, q1, speed, accel = self._joint_move
        length = float(np.max(np.abs(q1 - q0)))
        if length < 1e-9:
            self.mode, self._joint_move = Mode.IDLE, None
            return
        remaining = length - self._mj_s
        if self._mj_sd**2 / (2 * accel) >= remaining:
            self._mj_sd = max(0.0, self._mj_sd - accel * dt)
        else:
            self._mj_sd = min(speed, self._mj_sd + accel * dt)
        self._mj_s = min(length, self._mj_s + max(self._mj_sd, 1e-4) * dt)
        old = self.q.copy()
        self.q = q0 + (q1 - q0) * (self._mj_s / length)
        self.qd = (self.q - old) / dt
        t, _ = forward(self.q, self.tcp)
        old_pos = self.pos
        self.pos, self.rot = t[:3, 3].copy(), t[:3, :3].copy()
        self.velocity = np.concatenate([(self.pos - old_pos) / dt, np.zeros(3)])
        if self._mj_s >= length:
            self.mode, self._joint_move = Mode.IDLE, None
            self.qd = np.zeros(6)
            self.velocity = np.zeros(6)

    def _integrate(self, v: np.ndarray, dt: float) -> None:
        self.pos = self.pos + v[:3] * dt
        self.rot = rotvec_to_matrix(v[3:] * dt) @ self.rot

    def _track_joints(self, dt: float) -> None:
        """Damped least-squares steps of the joints onto the TCP pose, until they agree.

        One step per tick left a residual after a long tick (a loaded machine
        steps the arm by the real time missed, up to 50 ms), which the next
        tick, often a short one, paid off at residual/dt: a joint speed spike
        the lab world's safety check read as a real one and answered with a
        protective stop. Converged, ``qd`` is the joints' motion over this tick.
        """
        if self.mode == Mode.IDLE and self._joints_settled:
            return  # nothing moved: skip the 60 us of kinematics
        q0 = q = self.q
        for i in range(JOINT_TRACK_MAX_STEPS):
            t, jac = forward(q, self.tcp)
            err = np.concatenate([self.pos - t[:3, 3], rotation_error(self.rot, t[:3, :3])])
            e = float(np.linalg.norm(err))
            if e < 1e-10 and i == 0:
                self.qd = np.zeros(6)
                self._joints_settled = True
                return
            if e < JOINT_TRACK_TOLERANCE:
                break
            q = q + jac.T @ np.linalg.solve(jac @ jac.T + 1e-3 * np.eye(6), err)
        self._joints_settled = False
        self.q = q
        self.qd = (q - q0) / dt


def _cap(v: np.ndarray, limit: float) -> np.ndarray:
    n = float(np.linalg.norm(v))
    return v if n <= limit else v * (limit / n)


def _approach(v: np.ndarray, target: np.ndarray, max_step: float) -> np.ndarray:
    """``v`` moved toward ``target`` by at most ``max_step`` (Euclidean), landing on it exactly."""
    dv = target - v
    n = float(np.linalg.norm(dv))
    return target.copy() if n <= max_step else v + dv * (max_step / n)
