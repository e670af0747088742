"""A scripted operator: the task benchmark's hands, working through the operator node.

It does what a person feeling the palm would do: lower the open gripper onto
the rack, close, feel, and unless the palm says "90 deg, centre", open, turn
the wrist or shift the fingers the way the palm says, and try again; then
lift. It knows only what an operator knows: the palm's 3 x 3 stimulus (or
nothing, without tactile feedback) and the arm's pose from the robot's
heartbeat; it acts only through :meth:`OperatorNode.send_command`, so its
commands cross the same link, gate, clipping and deadman as a person's.

How a reading becomes a correction is the operator's learned mapping, in the
tactile contract's common view (columns along the tool's x, row 0 at the
fingertips). A 45 deg band turns the wrist +45 deg about the closing axis, a
135 deg band -45 deg (never beyond +-50 deg in all); a turn that overshoots
(45 becomes 135) is halved back, one that lands far off (0 deg) is undone and
tried the other way. Once the band is upright (or the turns have shrunk below
``min_turn_deg``), points off the centre line shift the fingers that way along
the tool's x (halved back when they cross the centre), and points that lean
turn the wrist by ``min_turn_deg``.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from common.config.typed import param
from common.rotation import matrix_to_rotvec, rotvec_to_matrix
from common.tactile.contract import MASKS, N_PATTERNS, classes_of, pattern_of
from common.wire.messages import ASSIST_PHASES

log = logging.getLogger(__name__)

#: the arm's pose in the robot heartbeat's stats (the arm panel reads the same keys)
POSE_KEYS = ("arm_x", "arm_y", "arm_z", "arm_rx", "arm_ry", "arm_rz")
#: what the task asks the palm to say before lifting: 90 deg, centre
TARGET_PATTERN = pattern_of(2, 0)
#: which way a felt angle class asks the wrist to turn about the tool's closing axis y
#: (+: a 45 deg band, -: a 135 deg band); a 0 deg band says "far off", not which way
ANGLE_SIGN = {0: 0, 1: 1, 2: 0, 3: -1}
#: contact points this far (cells, mean column) off the centre line are "left" or "right"
SIDE_CELLS = 0.5


class OperatorLike(Protocol):
    """What the scripted operator needs of the operator node."""

    def send_command(
        self, action: str, grip_level: int | None = None, velocity: tuple[float, ...] | None = None
    ) -> None: ...

    def snapshot(self) -> Any: ...


@dataclass
class ScriptedOperatorConfig:
    approach_depth_m: float = param(0.025, "how far below the start pose the fingers close (m)")
    lift_m: float = param(0.04, "how far to draw the pipette up along the tool's axis (m)")
    grip_level: int = param(16, "grip level of every close (1..31)")
    max_attempts: int = param(8, "grasps before giving up")
    shift_step_m: float = param(
        0.005, "one sideways correction (m): the position classes are 3 mm off centre"
    )
    search_steps_m: tuple[float, ...] = param(
        (0.008, -0.016, 0.024, -0.032),
        "sideways moves (m, along tool x, each from the last) when a close feels nothing",
    )
    max_turn_deg: float = param(
        50.0, "the wrist never turns further from the start (the arm nears a singularity)"
    )
    turn_step_deg: float = param(45.0, "the first wrist correction (deg)")
    min_turn_deg: float = param(
        12.0, "the finest wrist correction (deg): below it, turning gives way to shifting"
    )
    speed_m_s: float = param(0.08, "jog speed cap (m/s)")
    turn_speed_rad_s: float = param(0.5, "wrist turn speed cap (rad/s; the robot caps it too)")
    gain_per_s: float = param(4.0, "jog speed per metre (or radian) of error left (1/s)")
    tolerance_m: float = param(0.001, "a move is done within this distance (m)")
    tolerance_rad: float = param(0.012, "and within this angle (rad)")
    jog_period_s: float = param(0.05, "jog commands while moving (the robot wants one per 100 ms)")
    settle_s: float = param(0.25, "the palm must say the same this long before it is believed")
    close_wait_s: float = param(0.5, "after a close, the fingers are given this long to arrive")
    feel_timeout_s: float = param(3.0, "a close that feels nothing this long touched nothing")
    blind_close_s: float = param(1.5, "without feedback: how long a close is given to finish")
    release_s: float = param(0.6, "an open is given this long (and, with feedback, an empty palm)")
    move_timeout_s: float = param(15.0, "a move that has not arrived by then has failed")
    assist_timeout_s: float = param(
        30.0, "with the assist: held at most this long before letting go and correcting by hand"
    )


@dataclass
class Attempt:
    """One close: where the wrist was and what the palm said (None: nothing felt)."""

    turn_deg: float
    shift_m: float
    felt_pattern: int | None
    t_s: float
    truth: Any = None  # what the harness's observer saw at that moment (never the operator)


@dataclass
class Outcome:
    """What the operator did in one trial; the world's truth is the harness's business."""

    lifted: bool  # the operator decided to lift (it believed the grasp correct, or had no say)
    t_decision_s: float | None  # from the start to the decision to lift
    attempts: list[Attempt] = field(default_factory=list)
    gave_up: str | None = None


class SteadyPalm:
    """What the palm says, and since when: a reading is believed once held ``settle_s``."""

    def __init__(self, settle_s: float) -> None:
        self.settle_s = settle_s
        self.held: tuple[int | None, bool] | None = None
        self.since = 0.0

    def see(self, snap: Any, now: float) -> tuple[int | None, bool] | None:
        """The reading once it has held still long enough; None until then."""
        ok = snap.link_state == "ok"
        reading = (read_palm(snap.stimulus), says_lift(snap.stimulus)) if ok else None
        if reading is None or reading[0] is None or reading != self.held:
            self.held, self.since = reading, now
            return None
        return reading if now - self.since >= self.settle_s else None


#: how long an operator waits for the arm's pose to come back to the panel
POSE_GAP_S = 2.0


class ScriptedOperatorError(RuntimeError):
    """The arm did not do what the operator asked (no pose, a move timed out, a lost link)."""


def read_palm(stimulus: np.ndarray | None) -> int | None:
    """The pattern a 3 x 3 stimulus presents, as a person would name it; None when empty.

    The nearest of the contract's twelve masks by overlap of pressed cells
    (intersection over union). A partial band (one or two contact points)
    can fit several masks equally: the reader then assumes the pipette
    stands upright (90 deg, the rack's prior), then takes the mask holding
    more of the force. Lifting asks for more than the nearest name
    (:func:`says_lift`).
    """
    pressed = _pressed(stimulus)
    if pressed is None:
        return None
    s = np.nan_to_num(np.asarray(stimulus, dtype=float), nan=0.0, posinf=0.0, neginf=0.0)
    s = np.clip(s, 0.0, 1e6)  # garbage of any size weighs in, but never sums to infinity
    best, best_score = None, (-1.0, False, -1.0)
    for p in range(N_PATTERNS):
        mask = MASKS[p]
        iou = int((pressed & mask).sum()) / int((pressed | mask).sum())
        score = (iou, classes_of(p)[0] == 2, float(s[mask].sum()))
        if score > best_score:
            best, best_score = p, score
    return best


def says_lift(stimulus: np.ndarray | None) -> bool:
    """The palm says "90 deg, centre": two or three points, all on the centre line."""
    pressed = _pressed(stimulus)
    if pressed is None:
        return False
    centre = MASKS[TARGET_PATTERN]
    return not (pressed & ~centre).any() and int((pressed & centre).sum()) >= 2


def lean_and_side(stimulus: np.ndarray | None) -> tuple[int, float]:
    """What the contact points say beyond their name: which way they lean, where they sit.

    lean: +1 when the top point is right of the bottom one (a "/" band: turn
    as for 45 deg), -1 for "\\", 0 for neither or fewer than two rows.
    side: the points' mean column minus the centre one, in cells (+: right).
    """
    pressed = _pressed(stimulus)
    if pressed is None:
        return 0, 0.0
    rows, cols = np.nonzero(pressed)
    side = float(cols.mean()) - 1.0
    if len(set(rows.tolist())) < 2:
        return 0, side
    top = cols[rows == rows.min()].mean()
    bottom = cols[rows == rows.max()].mean()
    return int(np.sign(top - bottom)), side


def _pressed(stimulus: np.ndarray | None) -> np.ndarray | None:
    if stimulus is None:
        return None
    s = np.nan_to_num(np.asarray(stimulus, dtype=float), nan=0.0, posinf=0.0, neginf=0.0)
    pressed = s > 0
    return pressed if pressed.shape == MASKS[0].shape and pressed.any() else None


class ScriptedOperator:
    """Grasp, feel, correct, lift; ``feedback=False`` closes once where it is and lifts."""

    def __init__(
        self,
        node: OperatorLike,
        config: ScriptedOperatorConfig | None = None,
        *,
        feedback: bool = True,
        assist: bool = False,
        clock: Callable[[], float] = time.monotonic,
        stop: threading.Event | None = None,
    ) -> None:
        """``assist``: at the first wrong grasp felt, hold the robot's assist (arm_assist) until it
        stops, then feel again; correct by hand only if it did not align the grasp."""
        self.node = node
        self.config = config or ScriptedOperatorConfig()
        self.feedback = feedback
        self.assist = assist and feedback
        self.clock = clock
        self.stop = stop or threading.Event()

    # -- what the operator sees -------------------------------------------------------

    def pose(self) -> np.ndarray:
        """The arm's TCP pose from the newest robot heartbeat.

        A heartbeat without one (the robot's arm stream stale for a moment, which a busy
        machine makes happen; the page's panel then says so) is waited out, as an operator
        looking at the panel would, for up to ``POSE_GAP_S``.
        """
        stats = self.node.snapshot().robot_stats
        try:
            return np.array([float(stats[k]) for k in POSE_KEYS])
        except KeyError:
            try:
                return self.wait_for_pose(POSE_GAP_S)
            except ScriptedOperatorError:
                raise ScriptedOperatorError(
                    f"the robot's heartbeats carried no arm pose for {POSE_GAP_S:g} s"
                ) from None

    def wait_for_pose(self, timeout_s: float = 10.0) -> np.ndarray:
        end = self.clock() + timeout_s
        while self.clock() < end and not self.stop.is_set():
            snap = self.node.snapshot()
            if snap.link_state == "ok" and all(k in snap.robot_stats for k in POSE_KEYS):
                return self.pose()
            self.stop.wait(0.05)
        raise ScriptedOperatorError(f"no arm pose from the robot within {timeout_s:g} s")

    def feel(
        self, timeout_s: float, closing: bool = True, palm: SteadyPalm | None = None
    ) -> tuple[int | None, bool, np.ndarray | None]:
        """(pattern, "lift", the stimulus) once the palm has held still ``settle_s``.

        (None, False, None) when nothing is felt within ``timeout_s``. ``closing``: the
        fingers were just told to close (not after the assist, which closed and settled).
        ``palm``: what the operator has already watched it say (while holding the assist).
        """
        cfg = self.config
        if closing:
            self.stop.wait(cfg.close_wait_s)  # the fingers are still closing: not yet a grasp
        end = self.clock() + timeout_s
        palm = palm or SteadyPalm(cfg.settle_s)
        while self.clock() < end and not self.stop.is_set():
            snap = self.node.snapshot()
            reading = palm.see(snap, self.clock())
            if reading is not None:
                log.debug("palm reads %s from %s (robot: %s)", reading, snap.stimulus, snap.pattern)
                return (*reading, snap.stimulus)
            self.stop.wait(0.02)
        return None, False, None

    # -- what the operator does -------------------------------------------------------

    def move_to(self, target: np.ndarray) -> None:
        """Jog to a pose by the heartbeat's pose: proportional, capped, then stop."""
        cfg = self.config
        end = self.clock() + cfg.move_timeout_s
        r_target = rotvec_to_matrix(target[3:])
        while not self.stop.is_set():
            snap = self.node.snapshot()
            if snap.robot_stats.get("arm_stop_latched"):
                raise ScriptedOperatorError(
                    "someone pressed STOP: the robot refuses every jog until the lease holder "
                    "resumes (arm_resume)"
                )
            if snap.link_state != "ok":
                self.stop.wait(cfg.jog_period_s)  # the robot's deadman has stopped the arm
                if self.clock() > end:
                    break
                continue
            pose = self.pose()
            dp = target[:3] - pose[:3]
            dr = matrix_to_rotvec(r_target @ rotvec_to_matrix(pose[3:]).T)
            if np.linalg.norm(dp) <= cfg.tolerance_m and np.linalg.norm(dr) <= cfg.tolerance_rad:
                self.node.send_command("arm_jog_end")
                return
            if self.clock() > end:
                break
            v = _capped(cfg.gain_per_s * dp, cfg.speed_m_s)
            w = _capped(cfg.gain_per_s * dr, cfg.turn_speed_rad_s)
            self.node.send_command("arm_jog", velocity=(*v.tolist(), *w.tolist()))
            self.stop.wait(cfg.jog_period_s)
        self.node.send_command("arm_jog_end")
        raise ScriptedOperatorError(f"the arm did not reach {np.round(target, 4).tolist()}")

    def close(self) -> None:
        self.node.send_command("gripper_close", grip_level=self.config.grip_level)

    def release(self) -> None:
        """Open, and (with feedback) wait until the palm is empty."""
        self.node.send_command("gripper_open")
        end = self.clock() + self.config.release_s
        while self.clock() < end and not self.stop.is_set():
            self.stop.wait(0.02)
        if self.feedback:
            quiet_end = self.clock() + self.config.feel_timeout_s
            while self.clock() < quiet_end and not self.stop.is_set():
                if read_palm(self.node.snapshot().stimulus) is None:
                    return
                self.stop.wait(0.02)

    def grasp_and_lift(
        self,
        on_lift: Callable[[], None] | None = None,
        observe: Callable[[], Any] | None = None,
    ) -> Outcome:
        """One trial from the start pose; ``on_lift`` runs at the decision to lift.

        ``observe`` (the harness's, never the operator's) is called at every
        reading, and what it returns is kept with the attempt.
        """
        cfg = self.config
        t0 = self.clock()
        start = self.wait_for_pose()
        r_start = rotvec_to_matrix(start[3:])
        turn_deg, shift_m, searches = 0.0, 0.0, 0
        last_step = 0.0  # the last wrist correction (deg), 0 after a shift
        last_shift = 0.0  # the last sideways correction (m)
        outcome = Outcome(lifted=False, t_decision_s=None)
        assisted = False
        for _ in range(cfg.max_attempts):
            grasp = self._grasp_pose(start, r_start, turn_deg, shift_m)
            self.move_to(grasp)
            self.close()
            if not self.feedback:
                self.stop.wait(cfg.blind_close_s)
                return self._lift(grasp, t0, outcome, on_lift)
            felt, lift, stimulus = self.feel(cfg.feel_timeout_s)
            truth = observe() if observe is not None else None
            outcome.attempts.append(Attempt(turn_deg, shift_m, felt, self.clock() - t0, truth))
            if lift:
                return self._lift(grasp, t0, outcome, on_lift)
            # once a trial, at the first grasp that felt wrong (a miss first searches by hand)
            if self.assist and felt is not None and not assisted:
                assisted = True
                palm = SteadyPalm(cfg.settle_s)  # watched while the robot works, as a person would
                self.hold_assist(palm)
                felt, lift, stimulus = self.feel(cfg.feel_timeout_s, closing=False, palm=palm)
                truth = observe() if observe is not None else None
                outcome.attempts.append(Attempt(turn_deg, shift_m, felt, self.clock() - t0, truth))
                if lift:  # lifted from where the assist left the arm
                    return self._lift(self.pose(), t0, outcome, on_lift)
            self.release()
            if felt is None:
                if searches >= len(cfg.search_steps_m):
                    outcome.gave_up = "nothing felt anywhere the search reached"
                    return outcome
                shift_m += cfg.search_steps_m[searches]
                searches += 1
                continue
            angle, _ = classes_of(felt)
            lean, side = lean_and_side(stimulus)
            if angle == 2 or 0 < abs(last_step) < cfg.min_turn_deg:
                # upright enough, or turning no longer helps: centre the points, then straighten
                if abs(side) >= SIDE_CELLS:
                    if last_shift and side * last_shift < 0:
                        last_shift = -last_shift / 2.0  # past the centre: halve back
                    else:
                        last_shift = math.copysign(cfg.shift_step_m, side)
                    shift_m += last_shift
                    last_step = 0.0
                elif lean:
                    turn_deg += lean * cfg.min_turn_deg
                    last_step = 0.0
                continue  # nothing to correct (a single point): grasp again
            sign = ANGLE_SIGN[angle]
            if sign == 0:
                # far off (a 0 deg band): the last turn went the wrong way, or there was none
                step = -2.0 * last_step if last_step else cfg.turn_step_deg
            elif last_step and sign * last_step < 0:
                step = -last_step / 2.0  # overshot past 90 deg: halve back
            elif last_step:
                step = last_step  # not there yet: the same again
            else:
                step = sign * cfg.turn_step_deg
            new_turn = max(-cfg.max_turn_deg, min(cfg.max_turn_deg, turn_deg + step))
            last_step = new_turn - turn_deg
            turn_deg = new_turn
        outcome.gave_up = f"no 90 deg centre grasp in {cfg.max_attempts} attempts"
        return outcome

    def hold_assist(self, palm: SteadyPalm | None = None) -> str | None:
        """Hold the assist (an enable every jog period) until the robot says it stopped.

        The robot turns, shifts and re-grasps on its own (robot_side/node/assist.py);
        the heartbeat's ``assist_phase`` says when it is done. Returns the phase it
        ended in (None: not within ``assist_timeout_s``); the enable is let go either way.
        ``palm`` watches the palm meanwhile (it keeps rendering throughout).
        """
        cfg = self.config
        end = self.clock() + cfg.assist_timeout_s
        done = {ASSIST_PHASES.index(p) for p in ("aligned", "gave_up", "ended")}
        phase = None
        while self.clock() < end and not self.stop.is_set():
            self.node.send_command("arm_assist")
            snap = self.node.snapshot()
            if palm is not None:
                palm.see(snap, self.clock())
            code = snap.robot_stats.get("assist_phase")
            if code is not None and int(code) in done:
                phase = ASSIST_PHASES[int(code)]
                break
            self.stop.wait(cfg.jog_period_s)
        self.node.send_command("arm_jog_end")  # let go: the robot's assist ends at once
        log.info("assist held: %s", phase or "no end within the timeout")
        return phase

    def _grasp_pose(
        self, start: np.ndarray, r_start: np.ndarray, turn_deg: float, shift_m: float
    ) -> np.ndarray:
        """The start pose lowered, shifted along the tool's x, turned about its closing axis."""
        pose = start.copy()
        pose[:3] += r_start @ np.array([shift_m, 0.0, 0.0])
        pose[2] -= self.config.approach_depth_m
        turn = rotvec_to_matrix(r_start @ np.array([0.0, math.radians(turn_deg), 0.0]))
        pose[3:] = matrix_to_rotvec(turn @ r_start)
        return pose

    def _lift(
        self,
        grasp: np.ndarray,
        t0: float,
        outcome: Outcome,
        on_lift: Callable[[], None] | None,
    ) -> Outcome:
        outcome.lifted = True
        outcome.t_decision_s = self.clock() - t0
        if on_lift is not None:
            on_lift()
        up = grasp.copy()
        up[:3] -= rotvec_to_matrix(grasp[3:])[:, 2] * self.config.lift_m  # tool z points down
        self.move_to(up)
        return outcome


def _capped(v: np.ndarray, cap: float) -> np.ndarray:
    n = float(np.linalg.norm(v))
    return v if n <= cap else v * (cap / n)
