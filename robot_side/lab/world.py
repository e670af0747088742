"""The lab's physics: one MuJoCo model and data, stepped by one thread, read under a lock.

``LabWorld`` is the engine side only: it places the arm from joint angles,
drives the fingers, steps, and reports what the engine saw: per-taxel
normal forces, whether anything hit the table, where the gripper and the
pipettes are (``grasp_truth`` reads the ground truth off them), and camera
images on demand (a renderer is only created when somebody asks for an
image).
"""

from __future__ import annotations

import logging
import os
import threading
import time

import numpy as np

from robot_side.lab.config import LabWorldConfig, PipetteConfig
from robot_side.lab.model import (
    N_COLS,
    N_ROWS,
    PALM_HALF_M,
    axis_quat,
    build_mjcf,
    link_poses,
    pipette_placement,
    pipette_placements,
)

log = logging.getLogger(__name__)


def import_mujoco():
    """MuJoCo, with headless EGL rendering unless the caller chose a GL backend."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    try:
        import mujoco
    except ImportError as e:
        raise ImportError("the simulated lab needs MuJoCo: pip install 'deepxpalm[lab]'") from e
    return mujoco


class LabWorld:
    """One simulated lab. Thread-safe: every method takes ``lock``."""

    def __init__(self, config: LabWorldConfig | None = None) -> None:
        self.mj = mj = import_mujoco()
        self.config = cfg = config or LabWorldConfig()
        self.model = mj.MjModel.from_xml_string(build_mjcf(cfg))
        self.data = mj.MjData(self.model)
        self.lock = threading.RLock()
        m = self.model
        gid = lambda name: mj.mj_name2id(m, mj.mjtObj.mjOBJ_GEOM, name)  # noqa: E731
        self._taxel_index = np.full(m.ngeom, -1, dtype=np.int64)
        for pad in range(2):
            for r in range(N_ROWS):
                for c in range(N_COLS):
                    self._taxel_index[gid(f"taxel{pad}_{r}_{c}")] = (pad * N_ROWS + r) * N_COLS + c
        self.pipettes = pipette_placements(cfg)
        self._pipette_geom = np.full(m.ngeom, -1, dtype=np.int64)
        for i in range(len(self.pipettes)):
            self._pipette_geom[gid(f"pipette{i}")] = i
        self._table = gid("table")
        self._robot_geoms = np.zeros(m.ngeom, dtype=bool)
        for k in (1, 2):
            self._robot_geoms[gid(f"finger{k}_body")] = True
        self._robot_geoms[self._taxel_index >= 0] = True
        body = lambda name: mj.mj_name2id(m, mj.mjtObj.mjOBJ_BODY, name)  # noqa: E731
        self._link_mocap = [int(m.body_mocapid[body(f"link{j}")]) for j in range(6)]
        self._gripper_body = body("gripper")
        self._gripper_mocap = int(m.body_mocapid[body("flange_target")])
        self._gripper_joint = mj.mj_name2id(m, mj.mjtObj.mjOBJ_JOINT, "gripper")
        self._gripper_qpos = int(m.jnt_qposadr[self._gripper_joint])
        joints = [
            mj.mj_name2id(m, mj.mjtObj.mjOBJ_JOINT, f"pipette{i}")
            for i in range(len(self.pipettes))
        ]
        self._pipette_qpos = [int(m.jnt_qposadr[j]) for j in joints]
        self._pipette_dof = [int(m.jnt_dofadr[j]) for j in joints]
        self._pipette_body = [body(f"pipette{i}") for i in range(len(self.pipettes))]
        fingers = [mj.mj_name2id(m, mj.mjtObj.mjOBJ_JOINT, f"finger{k}") for k in (1, 2)]
        self._finger_qpos = [int(m.jnt_qposadr[j]) for j in fingers]
        self._finger_dof = [int(m.jnt_dofadr[j]) for j in fingers]
        self._renderers: dict[tuple[int, int], object] = {}
        self.q = np.zeros(6)
        #: the flange target's last place and its new one, glided between by the next step
        self._flange_from: tuple[np.ndarray, np.ndarray] | None = None
        self._flange_to: tuple[np.ndarray, np.ndarray] | None = None
        self.frames_rendered = 0
        self.steps = 0
        self.step_time_s = 0.0
        from robot_side.arm.sim.kinematics import HOME_Q

        self.set_arm(np.array(HOME_Q))
        self.gripper_to_flange()

    # -- the arm: placed, not integrated ---------------------------------------------

    def set_arm(self, q: np.ndarray, glide: bool = True) -> None:
        """Place the links and the gripper for joint angles ``q`` (the controller's).

        The gripper's flange target is not moved at once: the next :meth:`step`
        glides it there across its steps. ``LabServer`` moves the arm by the
        simulated time those steps take, so the glide is the arm's own motion,
        step by step. Placed once per batch, a world that owed several steps
        jerked the welded gripper in jumps and the pipette slid in the pads
        (2.7 mm per 40 mm lift placed every 8 steps, 12 mm every 25, against
        0.04 mm every step). ``glide=False`` puts it there for good, the steps
        of a batch already under way included (a trial's reset: a teleport).
        """
        links, flange = link_poses(q)
        quat = np.empty(4)
        with self.lock:
            self.q = np.array(q, dtype=float)
            d = self.data
            for mocap, t in zip(self._link_mocap, links, strict=True):
                d.mocap_pos[mocap] = t[:3, 3]
                self.mj.mju_mat2Quat(quat, t[:3, :3].ravel())
                d.mocap_quat[mocap] = quat
            self.mj.mju_mat2Quat(quat, flange[:3, :3].ravel())
            g = self._gripper_mocap
            self._flange_to = (flange[:3, 3].copy(), quat.copy())
            self._flange_from = (
                (d.mocap_pos[g].copy(), d.mocap_quat[g].copy()) if glide else self._flange_to
            )
            d.mocap_pos[g], d.mocap_quat[g] = self._flange_to

    def _glide_flange(self, fraction: float) -> None:
        """The flange target ``fraction`` of the way from its last place to its new one."""
        assert self._flange_from is not None and self._flange_to is not None
        (p0, q0), (p1, q1) = self._flange_from, self._flange_to
        if float(np.dot(q0, q1)) < 0.0:  # the shorter way round
            q1 = -q1
        quat = q0 + fraction * (q1 - q0)
        g = self._gripper_mocap
        self.data.mocap_pos[g] = p0 + fraction * (p1 - p0)
        self.data.mocap_quat[g] = quat / np.linalg.norm(quat)

    def gripper_to_flange(self) -> None:
        """Put the welded gripper at rest where its flange target is (no yank from the weld)."""
        with self.lock:
            d, a = self.data, self._gripper_qpos
            d.qpos[a : a + 3] = d.mocap_pos[self._gripper_mocap]
            d.qpos[a + 3 : a + 7] = d.mocap_quat[self._gripper_mocap]
            dof = int(self.model.jnt_dofadr[self._gripper_joint])
            d.qvel[dof : dof + 6] = 0.0
            self.mj.mj_forward(self.model, d)

    # -- the fingers -------------------------------------------------------------------

    def command_fingers(self, closure_m: float, force_n: float) -> None:
        """Each finger's servo: this far in from open, pushing with at most ``force_n``."""
        stroke = self.config.finger_stroke_mm / 1000
        with self.lock:
            self.data.ctrl[:] = min(max(closure_m, 0.0), stroke)
            self.model.actuator_forcerange[:] = (-force_n, force_n)

    def finger_closure_m(self) -> float:
        with self.lock:
            return float(np.mean([self.data.qpos[a] for a in self._finger_qpos]))

    def finger_speed_m_s(self) -> float:
        with self.lock:
            return float(np.mean(np.abs(self.data.qvel[self._finger_dof])))

    # -- the rack ------------------------------------------------------------------------

    def place_pipette(self, pipette: int, placement: PipetteConfig) -> None:
        """Put pipette ``pipette`` back in the rack at a new offset and tilt (a new trial)."""
        if not 0 <= pipette < len(self.pipettes):
            raise ValueError(f"no pipette {pipette}; the rack holds {len(self.pipettes)}")
        p = pipette_placement(self.config, placement)
        with self.lock:
            b = self._pipette_body[pipette]
            self.model.body_pos[b] = p.top
            self.model.body_quat[b] = axis_quat(p.axis)
            self.data.qpos[self._pipette_qpos[pipette]] = 0.0
            self.data.qvel[self._pipette_dof[pipette]] = 0.0
            self.pipettes[pipette] = p
            self.mj.mj_forward(self.model, self.data)

    def pipette_lift_m(self, pipette: int) -> float:
        """How far pipette ``pipette`` has been drawn up out of its rack hole (m)."""
        with self.lock:
            return float(self.data.qpos[self._pipette_qpos[pipette]])

    def pipette_top(self, pipette: int) -> np.ndarray:
        """The pipette's top end now (base frame)."""
        p = self.pipettes[pipette]
        return p.top + p.axis * self.pipette_lift_m(pipette)

    # -- stepping ------------------------------------------------------------------------

    def step(self, n: int = 1) -> None:
        """``n`` physics steps, the lock taken per step so readers never wait for a batch.

        The flange glides to where :meth:`set_arm` last put it, a share per step.
        """
        for k in range(n):
            with self.lock:
                if n > 1 and self._flange_from is not None:
                    self._glide_flange((k + 1) / n)
                t0 = time.perf_counter()
                self.mj.mj_step(self.model, self.data)
                self.step_time_s += time.perf_counter() - t0
                self.steps += 1
        self._flange_from = None

    @property
    def sim_time_s(self) -> float:
        return float(self.data.time)

    # -- what the engine saw ---------------------------------------------------------------

    def _contacts(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(geom1, geom2, normal force) of every contact; call with ``lock`` held."""
        d = self.data
        n = d.ncon
        if n == 0:
            e = np.zeros(0, dtype=np.int64)
            return e, e, np.zeros(0)
        c = d.contact
        # copies: the arrays are views of the engine's memory, which the next step rewrites
        g1 = np.array(c.geom1[:n])
        g2 = np.array(c.geom2[:n])
        adr = np.array(c.efc_address[:n])
        # elliptic cones: a contact's first constraint row is its normal force
        force = np.where(adr >= 0, d.efc_force[np.maximum(adr, 0)], 0.0)
        return g1, g2, force

    def taxel_forces(self) -> np.ndarray:
        """``FRAME_SHAPE`` normal force on each taxel, newtons, in the common view."""
        out = np.zeros(2 * N_ROWS * N_COLS)
        with self.lock:
            g1, g2, force = self._contacts()
        for g in (g1, g2):
            idx = self._taxel_index[g]
            hit = idx >= 0
            np.add.at(out, idx[hit], force[hit])
        return out.reshape(2, N_ROWS, N_COLS)

    def touching_pipette(self) -> int | None:
        """Index of a pipette a pad presses on, or None."""
        with self.lock:
            g1, g2, force = self._contacts()
        for a, b in ((g1, g2), (g2, g1)):
            hit = (self._pipette_geom[a] >= 0) & (self._taxel_index[b] >= 0) & (force > 0)
            if hit.any():
                return int(self._pipette_geom[a][hit][0])
        return None

    def table_collision(self) -> str | None:
        """What of the robot touches the table (a contact, or a link within clearance)."""
        with self.lock:
            g1, g2, _ = self._contacts()
            for a, b in ((g1, g2), (g2, g1)):
                hit = (a == self._table) & self._robot_geoms[b]
                if hit.any():
                    name = self.mj.mj_id2name(self.model, self.mj.mjtObj.mjOBJ_GEOM, int(b[hit][0]))
                    return f"{name} touches the table"
            links, flange = link_poses(self.q)
        clearance = self.config.table_clearance_m
        from robot_side.arm.sim.kinematics import DH_A, DH_D
        from robot_side.lab.model import LINK_RADIUS_M

        for j in range(1, 6):  # link 0 stands on the table
            t = links[j]
            for p in ((0, 0, 0), (0, 0, DH_D[j]), (DH_A[j], 0, DH_D[j])):
                z = (t @ np.array([*p, 1.0]))[2]
                if z - LINK_RADIUS_M[j] < clearance:
                    return f"link {j} reaches the table"
        hx, hy, hz = PALM_HALF_M
        corners = np.array(
            [[sx * hx, sy * hy, sz, 1.0] for sx in (-1, 1) for sy in (-1, 1) for sz in (0, 2 * hz)]
        )
        if float((corners @ flange.T)[:, 2].min()) < clearance:
            return "the gripper's palm reaches the table"
        return None

    def flange(self) -> np.ndarray:
        """The gripper's frame (4x4, base frame) as the engine has it."""
        with self.lock:
            t = np.eye(4)
            t[:3, :3] = self.data.xmat[self._gripper_body].reshape(3, 3)
            t[:3, 3] = self.data.xpos[self._gripper_body]
            return t

    # -- cameras, on demand ---------------------------------------------------------------------

    def camera_names(self) -> list[str]:
        m = self.model
        return [self.mj.mj_id2name(m, self.mj.mjtObj.mjOBJ_CAMERA, i) for i in range(m.ncam)]

    def render(self, camera: str = "overview", width: int = 320, height: int = 240) -> np.ndarray:
        """One RGB image (height, width, 3) uint8. Call from one thread only (its GL context)."""
        if camera not in self.camera_names():
            raise ValueError(f"no camera {camera!r}; cameras: {self.camera_names()}")
        key = (width, height)
        renderer = self._renderers.get(key)
        if renderer is None:
            renderer = self.mj.Renderer(self.model, height, width)
            self._renderers[key] = renderer
        with self.lock:
            renderer.update_scene(self.data, camera=camera)
        self.frames_rendered += 1
        return renderer.render()

    def close(self) -> None:
        for r in self._renderers.values():
            r.close()
        self._renderers.clear()
