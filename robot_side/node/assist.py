"""The assist: while the operator holds it, the robot aligns its grasp to what it feels.

Every correction an operator makes by hand (turn the wrist, shift, re-grasp)
waits a round trip of the link and the palm's settling. The assist makes
them on the robot from its own recognised pattern (what ``FramePipeline``
last recognised, refined by the band's measured angle and offset on the last
frame, ``robot_side/perception/band.py``): ease the fingers off the pipette,
shift the pad centre onto its axis, turn the wrist about the closing axis
until the pipette runs along the fingers (90 deg), close at the same grip
level, and judge again; then it stops and the operator decides to lift.

Safety is the operator's jog's, not a copy of it:

- it acts only while the enable is held: an ``arm_assist`` refreshed at the
  jog rate. It ends ``jog_timeout_s`` (the arm's jog deadman) after the last
  enable was sent, and every arm velocity it issues carries that enable's
  send time, so the arm's own deadman stops it at the same moment;
- its commands are ``arm_jog``, ``arm_jog_end`` and gripper commands given
  to ``Handover.act_for_holder`` (handover.py, handed in as ``act``): the
  stop latch, ``DEVICE_CALLS``, the
  arm driver's speed caps and workspace clipping and the recording, as for
  the holder's own. Its own targets are kept inside the box as well;
- any stop, the deadman, a lease change, the holder's own command or the
  enable's release ends it, and the arm stops. The command desk, which
  admits those, owns the assist and tells it (``hold``, ``end``,
  ``gripper_taken``); the assist never calls the desk.

Sign conventions (docs/tactile.md, ``grasp_truth.grasp_geometry``): the pads lie
in the tool's x-z plane, columns along +x ("right"), rows up along +z (the
fingertips, "up"), the fingers close along y. A turn of the tool by +phi
about its own y axis turns the pipette, as the pads see it, by +phi: the
angle class theta needs a turn of 90 - theta. Position class 1 lies along
``offset_direction`` (tool x, z) from the pad centre, class 2 against it;
the TCP (the pad centre) moves that way by the side offset.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from common.recording.channels import Recorder
from common.rotation import matrix_to_rotvec, rotvec_to_matrix
from common.tactile.contract import ANGLES_DEG, classes_of, pattern_of
from common.tactile.synthetic import offset_direction
from common.wire.messages import ASSIST_PHASES, Command
from robot_side.arm.base import TELEMETRY_POSE_KEYS, ArmLimits
from robot_side.node.config import AssistConfig
from robot_side.node.device_calls import DEFAULT_CLOSE_LEVEL
from robot_side.perception.band import Band, measure_band

if TYPE_CHECKING:
    from robot_side.node.frame_pipeline import FramePipeline
    from robot_side.node.workers import DeviceWorkers

log = logging.getLogger(__name__)

#: the grasp the assist aims for: 90 deg centre, the pipette along the fingers
ALIGNED_PATTERN = pattern_of(2, 0)

PHASES = ASSIST_PHASES
PHASE_CODES = {name: i for i, name in enumerate(PHASES)}
#: phases in which the assist is moving something, or waits for a grasp to feel
TIMED = frozenset({"waiting", "release", "shift", "turn", "close"})


class Assist:
    """The reflex's state machine, stepped by the node loop at frame rate."""

    def __init__(
        self,
        config: AssistConfig,
        pipeline: FramePipeline,
        workers: DeviceWorkers,
        *,
        act: Callable[[Command, int | None], bool],
        stop_latched: Callable[[], bool],
        grip_level: Callable[[], int | None],
        limits: ArmLimits | None,
        now: Callable[[], int],
        recorder: Recorder | None,
        announce: Callable[[], None],
    ) -> None:
        """``act``: a command on the holder's path (False: refused); ``stop_latched``:
        whether an operator's stop holds the arm; ``grip_level``: the level of the holder's
        newest gripper_close (None: none yet)."""
        self.config = config
        self.act = act
        self.stop_latched = stop_latched
        self.grip_level = grip_level
        self.pipeline = pipeline
        self.workers = workers
        self.limits = limits
        self.now = now
        self.recorder = recorder
        self.announce = announce
        self.phase = "off"
        self.why = ""
        self.regrasps = 0
        self.steps = 0  # commands issued, over the node's life
        self._enable_ns: int | None = None  # the newest enable's send time (our clock)
        self._phase_since = 0
        self._seq = 0
        self._level = DEFAULT_CLOSE_LEVEL
        self._contact_since: int | None = None
        self._start: np.ndarray | None = None  # the TCP pose when the phase began
        self._shift_to = np.zeros(3)  # where the re-grasp's shift takes the TCP (base frame)
        self._turn_by = 0.0  # the re-grasp's turn about the tool's y (rad)
        self._arm_moving = False
        self._turned_deg = 0.0
        self._eased = False  # our ease left the fingers off the pipette, and nothing closed them

    # ------------------------------------------------------ the operator's side
    def hold(self, enable_ns: int, now: int) -> str | None:
        """An admitted enable from the holder; a refusal reason (counter) or None."""
        if self.limits is None or "arm" not in self.workers.workers:
            return "assist_refused_no_arm"
        if self.pipeline.render.mode == "direct":
            return "assist_refused_direct_mode"  # no recognised pattern to align to
        self._enable_ns = enable_ns
        if self.phase == "off":
            self.regrasps = 0
            self._turned_deg = 0.0  # planned turns since the enable was pressed
            self._enter("waiting", now, "enable held")
        return None

    def gripper_taken(self) -> None:
        """The holder commanded the gripper: where the fingers are is theirs now, not ours."""
        self._eased = False

    def end(self, why: str) -> None:
        """A stop, the deadman, a lease change or the operator's own command: stop now."""
        if self.phase in ("off", "ended"):
            return
        self._stop_moving(why)
        self._enter("ended", self.now(), why)

    # ------------------------------------------------------------- the loop
    def step(self, now: int) -> None:
        """One turn of the reflex; never waits (commands go to the device workers)."""
        if self.phase == "off":
            return
        assert self.limits is not None and self._enable_ns is not None
        if now - self._enable_ns > self.limits.jog_timeout_s * 1e9:
            released = "enable released" if self.phase != "ended" else self.why
            self._stop_moving(released)
            self._enter("off", now, released)
            return
        if self.stop_latched():
            self.end("stop latched")
            return
        phase = self.phase
        if phase in TIMED and now - self._phase_since > self.config.phase_timeout_s * 1e9:
            self._stop_moving("phase timed out")
            self._enter("gave_up", now, f"{phase} unfinished in {self.config.phase_timeout_s} s")
            return
        getattr(self, f"_step_{phase}", lambda now: None)(now)

    def _step_waiting(self, now: int) -> None:
        stim = self.pipeline.last_stimulus
        if self._eased and (stim is None or not stim.contact):
            # an assist that lapsed mid re-grasp (the enable's deadman on a lossy link, a
            # stop) left the fingers eased off: nothing to feel until they close again
            self._close(now, "the fingers were left eased off")
            return
        # the pattern the operator felt and answered by holding the assist: no settling
        pattern = self._felt(now, since=self._phase_since, settle_ms=0.0)
        if pattern is None:
            return
        band = self._band()
        if self._aligned(pattern, band, now):
            return
        grip = self.grip_level()  # the operator's close, not where it stalled
        self._level = grip if grip is not None else DEFAULT_CLOSE_LEVEL
        self._regrasp(pattern, band, now)

    def _aligned(self, pattern: int, band: Band | None, now: int) -> bool:
        """90 deg centre recognised, and the band itself near 90 deg and centred (if measured)."""
        if pattern != ALIGNED_PATTERN:
            return False
        if band is not None:
            if abs(band.angle_deg - 90.0) > self.config.aligned_within_deg:
                return False  # "90" by class, yet far enough off to be another: turn the rest
            if math.hypot(*band.offset_mm) > self.config.centred_within_mm:
                return False  # "centre" by class, yet near the side's edge: shift the rest
        self._enter("aligned", now, f"90 deg centre recognised{_measured(band)}")
        return True

    def _band(self) -> Band | None:
        """The band on the last frame: its measured angle and offset (None: no band to see)."""
        frame = self.pipeline.last_frame
        return None if frame is None else measure_band(frame)

    def _regrasp(self, pattern: int, band: Band | None, now: int) -> None:
        """Plan the shift and the turn from one look at the frame; ease the fingers off."""
        pose = self._pose()
        if pose is None:
            return  # the arm's first reading is still to come
        self.regrasps += 1
        shift_tool, wanted = plan_regrasp(self.config, band, pattern, self._turned_deg)
        shift = rotvec_to_matrix(pose[3:]) @ shift_tool / 1000
        self._shift_to = self._inside_box(pose[:3] + shift)
        limit = self.config.max_turn_deg
        turn = max(-limit, min(limit, self._turned_deg + wanted)) - self._turned_deg
        self._turned_deg += turn
        self._turn_by = math.radians(turn)
        shift_mm = np.round(shift * 1000, 1).tolist()
        # just off the pipette, not the whole stroke: the close back takes 0.15 s, not 0.8
        self._issue(Command(seq=0, t_send_ns=0, action="gripper_ease"))
        self._eased = "gripper" in self.workers.workers
        self._enter(
            "release",
            now,
            f"pattern {pattern}{_measured(band)}: shift {shift_mm} mm, turn {turn:.0f} deg",
        )

    def _step_release(self, now: int) -> None:
        """Move once the fingers are off the pipette (or this scene has no gripper to open)."""
        if now - self._phase_since < self.config.release_ms * 1e6:
            return
        stim = self.pipeline.last_stimulus
        no_gripper = "gripper" not in self.workers.workers
        if no_gripper or stim is None or not stim.contact:
            self._begin_shift(now)

    def _begin_shift(self, now: int) -> None:
        self._start = self._pose()
        self._enter("shift", now, f"to {np.round(self._shift_to, 4).tolist()}")

    def _step_shift(self, now: int) -> None:
        pose = self._pose()
        if pose is None:
            return
        error = self._shift_to - pose[:3]
        if float(np.linalg.norm(error)) * 1000 <= self.config.position_tolerance_mm:
            self._stop_moving("shift done")
            self._start = pose
            self._enter("turn", now, f"by {math.degrees(self._turn_by):.0f} deg")
            return
        v = _capped(self.config.gain_per_s * error, self.config.shift_speed_m_s)
        self._jog(np.concatenate([v, np.zeros(3)]))

    def _step_turn(self, now: int) -> None:
        pose, start = self._pose(), self._start
        if pose is None or start is None:
            return
        r0 = rotvec_to_matrix(start[3:])
        turned = float(matrix_to_rotvec(r0.T @ rotvec_to_matrix(pose[3:]))[1])
        error = self._turn_by - turned
        if abs(math.degrees(error)) <= self.config.angle_tolerance_deg:
            self._stop_moving("turn done")
            self._close(now, "turn done")
            return
        w = float(np.clip(self.config.gain_per_s * error, -1, 1)) * self.config.turn_speed_rad_s
        self._jog(np.concatenate([np.zeros(3), w * r0[:, 1]]))

    def _step_close(self, now: int) -> None:
        pattern = self._felt(now, since=self._phase_since)
        if pattern is None:
            return
        band = self._band()
        if self._aligned(pattern, band, now):
            return
        if self.regrasps >= self.config.max_regrasps:
            self._enter("gave_up", now, f"pattern {pattern} after {self.regrasps} re-grasps")
        else:
            self._regrasp(pattern, band, now)

    # ------------------------------------------------------------ helpers
    def _close(self, now: int, why: str) -> None:
        self._issue(Command(seq=0, t_send_ns=0, action="gripper_close", grip_level=self._level))
        self._eased = False
        self._contact_since = None
        self._enter("close", now, f"{why}: closing at grip level {self._level}")

    def _felt(self, now: int, since: int, settle_ms: float | None = None) -> int | None:
        """The pattern recognised with contact held ``settle_ms`` (default: the config's)
        on frames captured after ``since``."""
        settle = self.config.settle_ms if settle_ms is None else settle_ms
        stim = self.pipeline.last_stimulus
        captured = self.pipeline.last_capture_ns
        if stim is None or not stim.contact or stim.pattern is None or captured is None:
            self._contact_since = None
            return None
        if captured < since:
            return None
        if self._contact_since is None:
            self._contact_since = captured
        if captured - self._contact_since < settle * 1e6:
            return None
        return stim.pattern

    def _pose(self) -> np.ndarray | None:
        state = self.workers.arm_readings()
        if not all(k in state for k in TELEMETRY_POSE_KEYS):
            return None
        return np.array([state[k] for k in TELEMETRY_POSE_KEYS])

    def _inside_box(self, xyz: np.ndarray) -> np.ndarray:
        lim, margin = self.limits, self.config.box_margin_m
        lo = np.array(lim.workspace_min) + margin
        hi = np.array(lim.workspace_max) - margin
        return np.minimum(np.maximum(xyz, lo), hi)

    def _jog(self, velocity: np.ndarray) -> None:
        self._arm_moving = True
        self._issue(Command(seq=0, t_send_ns=0, action="arm_jog", velocity=tuple(velocity)))

    def _stop_moving(self, why: str) -> None:
        """The arm stops (``arm_jog_end``: the assist latches nothing); a moving gripper holds."""
        if self._arm_moving or self.phase in ("shift", "turn"):
            self._issue(Command(seq=0, t_send_ns=0, action="arm_jog_end"))
            self._arm_moving = False
        if self.phase in ("release", "close") and why not in ("shift done", "turn done"):
            self._issue(Command(seq=0, t_send_ns=0, action="gripper_hold"))

    def _issue(self, cmd: Command) -> None:
        """Through the holder's path: the stop latch, DEVICE_CALLS, the arm's clipping."""
        self._seq += 1
        cmd.seq, cmd.t_send_ns = self._seq, self.now()
        self.steps += 1
        self.act(cmd, self._enable_ns)

    def _enter(self, phase: str, now: int, why: str) -> None:
        self.phase, self.why, self._phase_since = phase, why, now
        log.info("assist %s: %s", phase, why)
        self.announce()  # every phase change is in the next heartbeat at once
        if self.recorder is not None:
            self.recorder.write(
                "robot/assist",
                now,
                {"phase": phase, "why": why, "regrasps": self.regrasps, "steps": self.steps},
            )

    def stats(self) -> dict[str, Any]:
        """For the heartbeat: the phase (``PHASES``); re-grasps and commands issued once
        there are any (a heartbeat carries at most 64 stats)."""
        out = {"assist_phase": float(PHASE_CODES[self.phase])}
        if self.steps:
            out["assist_regrasps"] = float(self.regrasps)
            out["assist_steps"] = float(self.steps)
        return out


def plan_regrasp(
    config: AssistConfig, band: Band | None, pattern: int, turned_deg: float
) -> tuple[np.ndarray, float]:
    """(shift in tool x, y, z, mm; turn about the tool's y, deg) onto 90 deg centre.

    The band's geometry when the frame has one: the CNN names a class every
    45 deg and a side from 3 mm, and a tilted pipette meets the pads up to
    10 mm off centre at angles between the classes (a whole-class turn from a
    band at 67 deg ends at 112, "90" to the CNN and "135" to the world). The
    recognised class only when the frame has no band: its side by
    ``side_offset_mm``, its angle, and for 0 deg (far off either way) an
    eighth turn, after which the next grasp says which way. ``turned_deg``: the
    turns planned since the enable was pressed (the nearer of a band's two
    readings is taken from there).
    """
    if band is not None:
        ox, oz = band.offset_mm
        shift = _capped(np.array([ox, 0.0, oz]), config.max_shift_mm)
        wanted = 90.0 - band.angle_deg  # the pads cannot tell a band from its half turn:
        wanted = min((wanted, wanted - 180.0, wanted + 180.0),  # the nearer of the two
                     key=lambda w: abs(turned_deg + w))  # fmt: skip
        return shift, wanted
    angle_class, position = classes_of(pattern)
    dx, dz = offset_direction(angle_class)
    side = {0: 0.0, 1: 1.0, 2: -1.0}[position] * config.side_offset_mm
    wanted = 90.0 - ANGLES_DEG[angle_class] if angle_class else 45.0
    return np.array([dx * side, 0.0, dz * side]), wanted


def _measured(band: Band | None) -> str:
    if band is None:
        return ""
    return f" (the band at {band.angle_deg:.0f} deg, {math.hypot(*band.offset_mm):.1f} mm off)"


def _capped(v: np.ndarray, cap: float) -> np.ndarray:
    n = float(np.linalg.norm(v))
    return v if n <= cap else v * (cap / n)
