"""The task benchmark: does the palm help a (scripted) operator grasp a pipette right?

One *cell* is a link scenario and a feedback condition: the lab world
(started here, so the experimenter can re-place the pipette between trials
and read the truth), the robot node as its own process on that world
(`running_world`), the link simulator between it and the operator node
(which runs here; its servos are the recording bus, since the scripted
operator reads the stimulus and has no palm), and
:class:`operator_side.scripted.ScriptedOperator` acting through the operator
node. Each trial puts the rack's one pipette at a seeded tilt and offset the
operator does not know; the operator lowers, closes, feels and corrects until
the palm says "90 deg, centre" (or, without feedback, closes once), then
lifts. A trial succeeds when, at the decision to lift, the world's ground
truth is 90 deg centre and the lift draws the pipette out of its hole.

Feedback conditions: ``mask`` (the robot's CNN picks the pattern and the
stimulus is its mask), ``direct`` (the frame downsized, no CNN), ``none``
(the operator ignores the palm).
"""

from __future__ import annotations

import json
import logging
import tempfile
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from common.config import config_toml, from_dict
from common.tactile import pattern_name
from common.transport import free_loopback_ports
from deploy.demo import (
    fit_command_timing,
    netsim_args,
    spawn_cli,
    stop_child,
    wait_for_robot,
)
from deploy.scene import Scene, load_scene_dict

log = logging.getLogger(__name__)

FEEDBACKS = ("mask", "direct", "none")
SCENARIOS = ("lan", "intercontinental", "bad_day")
#: the rack's pipette, per trial: tilt uniform in +-this (deg) ...
TILT_RANGE_DEG = 35.0
#: ... and offset along the rack row uniform in +-this (m)
OFFSET_RANGE_M = 0.004
#: a lift that draws the pipette at least this far (mm) out of its hole took it
LIFTED_MM = 25.0


@dataclass(frozen=True)
class TrialSetup:
    index: int
    tilt_deg: float
    offset_m: float


def trial_setups(seed: int, trials: int) -> list[TrialSetup]:
    """The seeded placements: the same for every cell, so cells compare trial by trial."""
    rng = np.random.default_rng(seed)
    tilts = rng.uniform(-TILT_RANGE_DEG, TILT_RANGE_DEG, trials)
    offsets = rng.uniform(-OFFSET_RANGE_M, OFFSET_RANGE_M, trials)
    return [
        TrialSetup(i, round(float(t), 2), round(float(x), 5))
        for i, (t, x) in enumerate(zip(tilts, offsets, strict=True))
    ]


def run_cell(
    scenario: str,
    feedback: str,
    setups: list[TrialSetup],
    *,
    world_seed: int = 0,
    workdir: Path | None = None,
) -> dict[str, Any]:
    """Every trial of one cell, from fresh processes; the trials and a summary."""
    from operator_side.node import build_operator_node
    from operator_side.scripted import ScriptedOperator
    from robot_side.lab.config import LabWorldConfig, PipetteConfig
    from robot_side.lab.process import LabWorldProcess

    if feedback not in FEEDBACKS:
        raise ValueError(f"feedback must be one of {FEEDBACKS}, not {feedback!r}")
    workdir = workdir or Path(tempfile.mkdtemp(prefix=f"deepxpalm-task-{scenario}-{feedback}-"))
    workdir.mkdir(parents=True, exist_ok=True)
    scene = _scene(scenario, feedback)
    world = LabWorldProcess(LabWorldConfig(seed=world_seed, pipettes=[PipetteConfig()])).start()
    procs: list[tuple[str, Any, Path]] = []
    errors: list[str] = []
    stop = threading.Event()
    node = None
    thread = None
    trials: list[dict[str, Any]] = []
    t_cell = time.monotonic()
    try:
        addresses = workdir / "world.json"
        addresses.write_text(json.dumps(world.addresses))
        for device in ("tactile", "gripper", "arm"):
            getattr(scene.robot, device)["running_world"] = str(addresses)
        robot_tel, robot_cmd, op_tel, op_cmd = (
            f"tcp://127.0.0.1:{p}" for p in free_loopback_ports(4)
        )
        scene.robot.link.telemetry_endpoint = robot_tel
        scene.robot.link.command_endpoint = robot_cmd
        scene.operator.link.telemetry_endpoint = op_tel
        scene.operator.link.command_endpoint = op_cmd
        fit_command_timing(scene)
        robot_cfg = workdir / "robot.toml"
        robot_cfg.write_text(config_toml(scene.robot, "robot"))
        procs.append(
            (
                "robot",
                spawn_cli(["robot", "--config", str(robot_cfg)], workdir / "robot.log"),
                workdir / "robot.log",
            )
        )
        endpoints = (robot_tel, robot_cmd, op_tel, op_cmd)
        procs.append(
            (
                "netsim",
                spawn_cli(netsim_args(scene, endpoints), workdir / "netsim.log"),
                workdir / "netsim.log",
            )
        )
        node = build_operator_node(scene.operator)
        thread = threading.Thread(target=node.run, args=(stop,), name="operator", daemon=True)
        thread.start()
        wait_for_robot(node, procs, stop, errors)
        if errors:
            raise RuntimeError("; ".join(errors))
        hands = ScriptedOperator(node, feedback=feedback != "none", stop=stop)
        hands.wait_for_pose(timeout_s=30.0)
        for setup in setups:
            trials.append(_trial(world, hands, setup))
            for name, proc, path in procs:
                if proc.poll() is not None:
                    raise RuntimeError(f"{name} stopped during the trials; see {path}")
    finally:
        stop.set()
        if thread is not None:
            thread.join(timeout=10)
        for name, proc, path in reversed(procs):
            stop_child(proc, name, errors, path)
        world_stats = world.stats() if world.running else {}
        world.stop()
    return {
        "scenario": scenario,
        "feedback": feedback,
        "trials": trials,
        "summary": summarise(trials),
        "cell_s": round(time.monotonic() - t_cell, 1),
        "world": {k: world_stats.get(k) for k in ("real_time_factor", "step_cost_us")},
        "errors": errors,
        "logs": str(workdir),
    }


def _scene(scenario: str, feedback: str) -> Scene:
    mode = "direct" if feedback == "direct" else "mask"
    data = load_scene_dict("lab", [f"robot.render.mode={mode}"])
    scene: Scene = from_dict(Scene, data, where="")
    scene.network.enabled = True
    scene.network.scenario = scenario
    # No palm to feel it: a simulated STS bus would answer from a thread of this process,
    # which three cells side by side starve past its reply window at connect.
    scene.operator.servos = {"kind": "recording"}
    return scene


def _trial(world: Any, hands: Any, setup: TrialSetup) -> dict[str, Any]:
    from operator_side.scripted import ScriptedOperatorError

    hands.release()
    world.reset_trial(0, setup.offset_m, setup.tilt_deg)
    clock_at_start = world.stats()
    time.sleep(0.3)  # the next heartbeats carry the home pose
    truth_at_lift: dict[str, Any] = {}
    pose_at_lift: list[np.ndarray] = []

    def at_lift() -> None:
        truth_at_lift.update(world.grasp())
        pose_at_lift.append(hands.pose())

    row: dict[str, Any] = asdict(setup)
    try:
        outcome = hands.grasp_and_lift(at_lift, observe=lambda: world.grasp().get("pattern"))
    except ScriptedOperatorError as e:
        hands.node.send_command("arm_jog_end")  # a STOP (arm_stop) would latch the next trials
        stats = world.stats()
        stops = stats["protective_stops"]
        row.update(success=False, correct_grasp=False, lifted_mm=0.0, error=str(e), stops=stops)
        row.update(_trial_clock(clock_at_start, stats))
        log.warning("task trial %s failed: %s (protective stops: %s)", setup, e, stops)
        return row
    time.sleep(0.2)
    lifted_mm = world.pipette_lift_mm(0)
    # How far the tool rose (the heartbeat's pose): beside lifted_mm, what slipped in the pads.
    tool_mm = (
        1000 * float(np.linalg.norm(hands.pose()[:3] - pose_at_lift[0][:3]))
        if pose_at_lift
        else 0.0
    )
    correct = truth_at_lift.get("pattern") == 6
    row.update(
        success=bool(outcome.lifted and correct and lifted_mm >= LIFTED_MM),
        correct_grasp=bool(outcome.lifted and correct),
        lifted_mm=round(lifted_mm, 1),
        tool_lift_mm=round(tool_mm, 1),
        t_decision_s=None if outcome.t_decision_s is None else round(outcome.t_decision_s, 2),
        attempts=len(outcome.attempts) or 1,
        felt=[a.felt_pattern for a in outcome.attempts],
        felt_truth=[a.truth for a in outcome.attempts],
        truth=None
        if truth_at_lift.get("pattern") is None
        else pattern_name(truth_at_lift["pattern"]),
        truth_tilt_deg=None
        if truth_at_lift.get("tilt_deg") is None
        else round(truth_at_lift["tilt_deg"], 1),
        gave_up=outcome.gave_up,
    )
    row.update(_trial_clock(clock_at_start, world.stats()))
    log.info("task trial %s", row)
    return row


def _trial_clock(start: dict[str, Any], end: dict[str, Any]) -> dict[str, Any]:
    """The world's sim/wall over the trial, its slowest 1 s window, and whether it fell behind."""
    from robot_side.lab.clock import BEHIND_SIM_WALL, sim_wall_between

    ratio = sim_wall_between(start, end)
    lowest = end.get("sim_wall_lowest")
    return {
        "sim_wall": None if ratio is None else round(ratio, 3),
        "sim_wall_lowest": None if lowest is None else round(lowest, 3),
        "behind": ratio is not None and ratio < BEHIND_SIM_WALL,
    }


def summarise(trials: list[dict[str, Any]]) -> dict[str, Any]:
    """Success rate (with a 95 % Wilson interval) and time to a correct grasp."""
    n = len(trials)
    wins = sum(t["success"] for t in trials)
    times = [t["t_decision_s"] for t in trials if t["success"] and t.get("t_decision_s")]
    # How much less than the tool the pipette rose, over the correct grasps it lifted
    slips = [
        t["tool_lift_mm"] - t["lifted_mm"]
        for t in trials
        if t["correct_grasp"] and t.get("tool_lift_mm") is not None
    ]
    lo, hi = wilson(wins, n)
    clocks = [t["sim_wall"] for t in trials if t.get("sim_wall") is not None]
    return {
        "trials": n,
        "successes": wins,
        "success_rate": wins / n if n else None,
        "success_ci95": [lo, hi],
        "correct_grasps": sum(t["correct_grasp"] for t in trials),
        "errors": sum(1 for t in trials if t.get("error")),
        "time_to_correct_s_p50": float(np.median(times)) if times else None,
        "time_to_correct_s_p90": float(np.percentile(times, 90)) if times else None,
        "attempts_mean": float(np.mean([t.get("attempts", 1) for t in trials])) if n else None,
        "slip_mm_p50": float(np.median(slips)) if slips else None,
        "slip_mm_max": float(np.max(slips)) if slips else None,
        # the world's sim/wall per trial: a trial below 0.98 fell behind real time
        "sim_wall_p50": float(np.median(clocks)) if clocks else None,
        "sim_wall_min": float(np.min(clocks)) if clocks else None,
        "trials_behind": sum(1 for t in trials if t.get("behind")),
    }


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float | None, float | None]:
    if n == 0:
        return None, None
    p = k / n
    d = 1 + z * z / n
    c = (p + z * z / (2 * n)) / d
    h = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return float(max(0.0, c - h)), float(min(1.0, c + h))
