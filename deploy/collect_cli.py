"""``deepxpalm collect``: labelled frames of every pattern at every grip level.

    deepxpalm collect --scene lab --out lab_session0.npz           # the simulated lab
    deepxpalm collect --scene covid_lab --out site.npz --present    # a person holds the pipette
    deepxpalm train --data lab_session0.npz --init default          # fine-tune on them
    deepxpalm collect --evaluate lab_session1.npz --model runs/perception/model.npz

With the arm (the default) the wrist turns the pipette's tilt on the pads
and shifts it along them, from the pose the arm is in at the start: above
the pipette, the fingers open around it. Every pose is checked against the
scene's [robot.arm.limits] box before the first move. ``--present`` leaves
the arm alone and asks a person to present the pipette for each pattern.

A deploy command because a scene (``deploy.scene``) says which devices to
build; the collecting itself is ``robot_side.perception.collect``.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from common.config.typed import from_dict
from common.devices.lifecycle import build_device
from common.process.command_line import add_overrides_argument
from common.progress import Progress
from common.tactile.contract import ANGLES_DEG, classes_of
from robot_side.perception.collect import POSITION_NAMES, CollectConfig, collect

log = logging.getLogger(__name__)


def _ints(text: str) -> list[int]:
    """ "0,4,7" or "1-31" or a mix."""
    out: list[int] = []
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        out.extend(range(int(lo), int(hi) + 1) if hi else [int(lo)])
    return out


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", default="lab", help="scene whose devices to use (default: lab)")
    parser.add_argument("--out", type=Path, help="the .npz to write")
    parser.add_argument(
        "--evaluate",
        type=Path,
        nargs="+",
        metavar="NPZ",
        help="no collection: print a model's accuracy on these sets per pattern and level",
    )
    parser.add_argument("--model", type=Path, help="with --evaluate: weights (default: shipped)")
    parser.add_argument("--patterns", type=_ints, help="e.g. 0-11 or 4,5 (default: all twelve)")
    parser.add_argument("--levels", type=_ints, help="grip levels, e.g. 1-31 (default: all)")
    parser.add_argument("--frames-per-level", type=int, help="frames kept per level (default 36)")
    parser.add_argument("--session", type=int, default=0, help="session id in the sensor column")
    parser.add_argument(
        "--world-config",
        type=Path,
        help="lab scenes: the world's settings TOML (seed, pipettes) for all three devices",
    )
    parser.add_argument(
        "--present", action="store_true", help="a person presents the pipette; the arm stays"
    )
    add_overrides_argument(parser, "robot.tactile.world_config=world.toml")


def _prompt(pattern: int, bar: Progress) -> None:
    angle, position = classes_of(pattern)
    bar.clear()  # the prompt takes the line; the next pattern-level draws the bar again
    input(
        f"pattern {pattern}: hold the pipette at {ANGLES_DEG[angle]} deg, "
        f"{POSITION_NAMES[position]}, "
        "between the open fingers, then press Enter "
    )


def run(args: argparse.Namespace) -> int:
    from deploy.scene import Scene, load_scene_dict
    from robot_side.arm import KINDS as ARM_KINDS
    from robot_side.gripper import KINDS as GRIPPER_KINDS
    from robot_side.tactile import KINDS as TACTILE_KINDS

    overrides = list(args.overrides)
    if args.world_config is not None:
        for family in ("tactile", "gripper", "arm"):
            overrides.append(f"robot.{family}.world_config={args.world_config}")
    if args.evaluate:
        from robot_side.perception.evaluate import evaluate, markdown

        acc = evaluate(args.evaluate, args.model)
        title = f"{args.model or 'shipped model'} on {', '.join(p.name for p in args.evaluate)}"
        print(markdown(acc, title), end="")
        return 0
    if args.out is None:
        raise SystemExit("deepxpalm collect: --out FILE.npz is required (or --evaluate)")
    scene = from_dict(Scene, load_scene_dict(args.scene, overrides), where="")
    config = CollectConfig(session=args.session)
    if args.patterns is not None:
        config.patterns = args.patterns
    if args.levels is not None:
        config.grip_levels = args.levels
    if args.frames_per_level is not None:
        config.frames_per_level = args.frames_per_level
    config.__post_init__()
    robot = scene.robot
    if robot.gripper.get("kind", "none") == "none":
        raise SystemExit("collect needs a gripper: the scene's [robot.gripper] kind is none")
    use_arm = not args.present
    if use_arm and robot.arm.get("kind", "none") == "none":
        raise SystemExit("the scene has no arm: use --present and hold the pipette")
    pads = build_device(TACTILE_KINDS, robot.tactile, "robot.tactile")
    gripper = build_device(GRIPPER_KINDS, robot.gripper, "robot.gripper")
    arm = build_device(ARM_KINDS, robot.arm, "robot.arm") if use_arm else None
    opened = []
    try:
        for device in (arm, gripper, pads):
            if device is not None:
                device.connect()
                opened.append(device)
        world = getattr(arm, "world", None) or getattr(gripper, "world", None)
        truth = (lambda: world.grasp()["pattern"]) if world is not None else None

        n = len(config.patterns) * len(config.grip_levels) * config.frames_per_level
        print(f"collecting {n} frames on scene {scene.scene.name} ...", flush=True)
        # a bar on a terminal, a line per tenth in a log (stderr: stdout keeps the results)
        levels = len(config.patterns) * len(config.grip_levels)
        with Progress("collect", levels, unit="pattern-levels") as bar:
            bar.update(0, force=True)
            data = collect(
                pads,
                gripper,  # type: ignore[arg-type]
                config,
                arm=arm,  # type: ignore[arg-type]
                present=None if use_arm else lambda pattern: _prompt(pattern, bar),
                truth=truth,
                progress=lambda done, total: bar.update(done, total),
            )
    finally:
        for device in reversed(opened):
            device.disconnect()
    data.meta["scene"] = scene.scene.name
    data.save(args.out)
    m = data.meta
    print(
        f"wrote {len(data)} frames to {args.out} in {m['seconds']} s; ground truth disagreed "
        f"with the set-up label at {m['truth_mismatches']} of {m['truth_checked']} grasps",
        file=sys.stdout,
    )
    return 0
