"""The world process: physics plus the three device simulators it feeds.

``LabServer`` owns a ``LabWorld`` and the unchanged wire-level simulators:
the UR controller (the world places the arm from its joints, and calls its
protective stop when the robot touches the table or leaves its joint limits),
the Robotiq URCap server (its fingers are the world's), and the tactile
board on a pty (its taxel forces are the world's). One thread steps the
physics in real time and the arm with it, on one clock: the controller's
motion advances by the simulated time each loop steps (``motion_clock =
"external"``), so a world that falls behind slows the arm alike. The drivers
in other processes talk to the simulators on their real wires, in real time.
"""

from __future__ import annotations

import base64
import logging
import math
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import numpy as np

from common.clocks.clock import Rate, now_s
from common.devices.lifecycle import as_hardware
from common.tactile.contract import N_GRIP_LEVELS
from robot_side.arm.sim.server import URSimConfig, URSimulator
from robot_side.gripper.base import GripLevels
from robot_side.gripper.sim import GripperModelConfig, GripperSimConfig, GripperSimServer
from robot_side.lab.camera_server import CameraServer
from robot_side.lab.clock import BEHIND_SIM_WALL, SimWallMeter
from robot_side.lab.config import LabWorldConfig, PipetteConfig
from robot_side.lab.grasp_truth import grasp_geometry, grasp_pattern
from robot_side.lab.model import TCP_OFFSET
from robot_side.lab.world import LabWorld
from robot_side.tactile.base import GraspTruth
from robot_side.tactile.board_sim import TactileBoardSimConfig, TactileBoardSimulator

log = logging.getLogger(__name__)

#: UR3e joint limits: +-360 deg on every joint (rad)
JOINT_LIMIT_RAD = 2 * math.pi
#: UR3e joint speed limits: 180 deg/s for base, shoulder, elbow; 360 deg/s for the wrists
JOINT_SPEED_LIMIT_RAD_S = (math.pi, math.pi, math.pi, 2 * math.pi, 2 * math.pi, 2 * math.pi)
#: a finger slower than this (m/s) while pressing on a pipette has stalled on it
STALL_SPEED_M_S = 0.002
#: the physics catches up at most this much wall time per loop (s): a stalled machine skips
MAX_CATCH_UP_S = 0.05
#: a world behind real time says so in its log at most this often (s)
BEHIND_LOG_EVERY_S = 30.0


class WorldFingers:
    """The gripper simulator's fingers, as the world moves them (a ``FingerDrive``)."""

    def __init__(self, world: LabWorld) -> None:
        self.world = world
        cfg = world.config
        self._m_per_count = cfg.finger_stroke_mm / 1000 / 255
        self._f0, self._f1 = cfg.finger_force_min_n, cfg.finger_force_max_n

    def command(self, position_counts: float, force_setting: int) -> None:
        force = self._f0 + (self._f1 - self._f0) * force_setting / 255
        self.world.command_fingers(position_counts * self._m_per_count, force)

    def position_counts(self) -> float:
        return self.world.finger_closure_m() / self._m_per_count

    def stalled_on_object(self) -> bool:
        return (
            self.world.touching_pipette() is not None
            and self.world.finger_speed_m_s() < STALL_SPEED_M_S
        )


class WorldContact:
    """The tactile board's contact forces and ground truth, from the world (a ``ContactSource``)."""

    def __init__(self, world: LabWorld, gripper: GripperSimServer, levels: GripLevels) -> None:
        self.world = world
        self.gripper = gripper
        self.levels = levels

    def contact_at(self, t_s: float) -> tuple[np.ndarray, GraspTruth]:
        force = self.world.taxel_forces()
        pattern = grasp_pattern(self.world) if force.max() >= 1.0 else None
        if pattern is None:
            return force, GraspTruth(pattern=None, grip_level=None)
        requested = self.gripper.model.read()["PRE"]
        level = self.levels.level_at(requested) or 1
        return force, GraspTruth(pattern=pattern, grip_level=max(1, min(N_GRIP_LEVELS, level)))


class LabServer:
    """Start with :meth:`start`; ``addresses()`` says where each simulator listens."""

    def __init__(self, config: LabWorldConfig | None = None) -> None:
        self.config = cfg = config or LabWorldConfig()
        self.world = LabWorld(cfg)
        self.ursim = URSimulator(URSimConfig(tcp_offset=TCP_OFFSET, motion_clock="external"))
        model = GripperModelConfig(object_present=False)
        self.gripper = GripperSimServer(GripperSimConfig(model=model))
        self.gripper.model.fingers = WorldFingers(self.world)
        self.board = TactileBoardSimulator(
            TactileBoardSimConfig(seed=cfg.seed),
            source=WorldContact(self.world, self.gripper, GripLevels()),
        )
        # every image is rendered on this one thread: a GL context is current on one at a time
        self._render_thread = ThreadPoolExecutor(1, thread_name_prefix="lab-render")
        self.cameras = CameraServer(self.render)
        self._quit = threading.Event()
        self._thread: threading.Thread | None = None
        self.protective_stops: list[str] = []
        self.loops = 0
        self.wall_s = 0.0
        self.sim_wall = SimWallMeter()
        self._behind_logged_at: float | None = None

    def start(self) -> LabServer:
        self.ursim.start()
        self.gripper.start()
        self.board.start()
        self.cameras.start()
        self._quit.clear()
        self._thread = threading.Thread(
            target=as_hardware(self._run), name="lab-physics", daemon=True
        )
        self._thread.start()
        return self

    def stop(self) -> None:
        self._quit.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self.cameras.stop()
        self.board.stop()
        self.gripper.stop()
        self.ursim.stop()
        self._render_thread.submit(self.world.close).result(timeout=5.0)
        self._render_thread.shutdown()

    def addresses(self) -> dict[str, Any]:
        cal = self.board.calibration
        return {
            "ur_host": self.ursim.host,
            "gripper_host": self.gripper.host,
            "gripper_port": self.gripper.port,
            "tactile_port": self.board.port,
            "camera_port": self.cameras.port,
            "tactile_zero": cal.zero_counts.tolist(),
            "tactile_gain": cal.gain_n_per_count.tolist(),
        }

    # -- the physics loop ----------------------------------------------------------------

    def _run(self) -> None:
        dt = self.config.timestep_s
        rate = Rate(1.0 / (4 * dt))  # a few steps per loop: 125 loops/s at 2 ms
        t_start = last = now_s()
        owed = 0.0
        q = self.ursim.joint_positions()
        while not self._quit.is_set():
            t = now_s()
            owed = min(owed + t - last, MAX_CATCH_UP_S)
            last = t
            n = int(owed / dt)
            if n > 0:
                # One clock: the arm moves by the simulated time these n steps take, and
                # the flange glides there across them. The joints are read under the world
                # lock, so a trial's reset (which teleports the arm home) is seen whole.
                self.ursim.advance(n * dt)
                with self.world.lock:
                    q = self.ursim.joint_positions()
                    self.world.set_arm(q)
                self.world.step(n)
                owed -= n * dt
            self._guard(q)
            self.loops += 1
            self.wall_s = now_s() - t_start
            self._clock_report(self.wall_s, self.world.steps * dt)
            rate.sleep()

    def _clock_report(self, wall_s: float, sim_s: float) -> None:
        """sim/wall per window; a world behind real time says so in its log."""
        ratio = self.sim_wall.update(wall_s, sim_s)
        if ratio is None or ratio >= BEHIND_SIM_WALL:
            return
        if self._behind_logged_at is None or wall_s - self._behind_logged_at > BEHIND_LOG_EVERY_S:
            self._behind_logged_at = wall_s
            log.warning(
                "lab: the world runs behind real time, sim/wall %.3f over the last %.1f s "
                "(the arm and the physics slow alike; the drivers, the operator and the "
                "link do not): the machine is too busy for it",
                ratio,
                self.sim_wall.window_s,
            )

    def _guard(self, q: np.ndarray) -> None:
        """Protective stop, as the controller's safety system would."""
        reason = self.world.table_collision()
        if reason is None and np.any(np.abs(q) > JOINT_LIMIT_RAD):
            reason = "a joint left its +-360 deg range"
        if reason is None:
            qd = np.abs(self.ursim.arm.qd)
            if np.any(qd > np.asarray(JOINT_SPEED_LIMIT_RAD_S)):
                reason = "a joint exceeded its speed limit"
        if reason is None or self.ursim.safety_mode != 1:
            return
        log.warning("lab: protective stop: %s", reason)
        self.protective_stops.append(reason)
        self.ursim.protective_stop()

    # -- what the parent may ask ------------------------------------------------------------

    def stats(self) -> dict[str, Any]:
        w = self.world
        sim_s = w.steps * w.config.timestep_s
        return {
            "physics_steps": w.steps,
            "step_cost_us": (w.step_time_s / w.steps * 1e6) if w.steps else None,
            "real_time_factor": (sim_s / w.step_time_s) if w.step_time_s else None,
            "sim_time_s": sim_s,
            "wall_time_s": self.wall_s,
            # the world's clock against the wall: the last window, the slowest since the
            # last trial reset, and how many windows since then fell behind
            "sim_wall": self.sim_wall.last,
            "sim_wall_lowest": self.sim_wall.lowest,
            "sim_wall_window_s": self.sim_wall.window_s,
            "sim_wall_windows_behind": self.sim_wall.windows_behind,
            "protective_stops": list(self.protective_stops),
            # the control script stopped by its RTDE watchdog: no kick read within its window
            "watchdog_trips": self.ursim.script.watchdog_trips,
            "camera_frames_rendered": w.frames_rendered,
            "safety_mode": self.ursim.safety_mode,
            "board": self.board.stats(),
        }

    def taxel_forces(self) -> list:
        return self.world.taxel_forces().tolist()

    def grasp(self) -> dict[str, Any]:
        i = self.world.touching_pipette()
        if i is None:
            return {"pipette": None, "pattern": None}
        theta, offset = grasp_geometry(self.world, i)
        return {
            "pipette": i,
            "pattern": grasp_pattern(self.world),
            "tilt_deg": theta,
            "offset_mm": offset,
            "lift_mm": self.world.pipette_lift_m(i) * 1000.0,
        }

    def reset_trial(self, pipette: int, x_m: float, tilt_deg: float) -> dict[str, Any]:
        """A new trial: the arm at home at rest, the pipette back in the rack at a new place.

        The experimenter's hands, in simulation: the operator under test
        never calls this. Open the gripper first (through the robot), or the
        pipette is placed between closed fingers.
        """
        with self.world.lock:
            self.ursim.teleport_home()
            self.world.set_arm(self.ursim.joint_positions(), glide=False)
            self.world.gripper_to_flange()
            self.world.place_pipette(int(pipette), PipetteConfig(x_m=x_m, tilt_deg=tilt_deg))
            self.protective_stops.clear()
            self.sim_wall.mark()
        return {"tcp_pose": self.tcp_pose(), "sim_time_s": self.world.sim_time_s}

    def pipette_lift_mm(self, pipette: int) -> float:
        """How far the pipette has been drawn out of its rack hole (mm): a lift's ground truth."""
        return self.world.pipette_lift_m(int(pipette)) * 1000.0

    def tcp_pose(self) -> list:
        return self.ursim.tcp_pose().tolist()

    def render(self, camera: str, width: int, height: int) -> Future:
        """An image of ``camera`` rendered now, on the render thread."""
        return self._render_thread.submit(self.world.render, camera, int(width), int(height))

    def camera_frame(self, camera: str = "overview", width: int = 320, height: int = 240) -> dict:
        t0 = time.perf_counter()
        image = self.render(camera, width, height).result(timeout=30.0)
        return {
            "width": image.shape[1],
            "height": image.shape[0],
            "rgb": base64.b64encode(np.ascontiguousarray(image).tobytes()).decode(),
            "render_ms": (time.perf_counter() - t0) * 1000,
            "sim_time_s": self.world.sim_time_s,
        }

    def camera_names(self) -> list[str]:
        return self.world.camera_names()


#: what the parent may call through the pipe
REMOTE_METHODS = frozenset(
    {
        "addresses",
        "stats",
        "taxel_forces",
        "grasp",
        "tcp_pose",
        "camera_frame",
        "camera_names",
        "reset_trial",
        "pipette_lift_mm",
    }
)
