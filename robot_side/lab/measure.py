"""What the lab's physics costs here: step time and real-time factor, idle and grasping.

``python -m robot_side.lab.measure`` steps the world (no simulators, no
wires: the physics alone) with the fingers open in the air, then closed on
the centre pipette at grip force, and prints one JSON line per phase.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from robot_side.arm.sim.kinematics import HOME_Q, KinematicArm
from robot_side.lab.config import LabWorldConfig
from robot_side.lab.world import LabWorld


def measure(steps: int = 2000) -> list[dict]:
    world = LabWorld(LabWorldConfig())
    arm = KinematicArm(q=np.array(HOME_Q))
    arm.move_l(arm.current_pose() - np.array([0, 0, 0.025, 0, 0, 0]), 0.1, 1.0)
    while arm.moving:
        arm.step(0.002)
    world.set_arm(arm.q)
    stroke = world.config.finger_stroke_mm / 1000
    out = []
    for phase, counts, force_n in (("open", 0, 20.0), ("grasping", 220, 120.0)):
        world.command_fingers(counts / 255 * stroke, force_n)
        world.step(250)  # settle
        t0 = time.perf_counter()
        world.step(steps)
        wall = time.perf_counter() - t0
        sim = steps * world.config.timestep_s
        out.append(
            {
                "phase": phase,
                "steps": steps,
                "timestep_ms": world.config.timestep_s * 1000,
                "step_cost_us": round(wall / steps * 1e6, 1),
                "real_time_factor": round(sim / wall, 2),
                "contacts": int(world.data.ncon),
                "taxels_pressed": int((world.taxel_forces() >= 1.0).sum()),
            }
        )
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m robot_side.lab.measure", description=__doc__)
    ap.add_argument("--steps", type=int, default=2000)
    for row in measure(ap.parse_args(argv).steps):
        print(json.dumps(row))


if __name__ == "__main__":
    main()
