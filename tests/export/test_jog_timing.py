"""On a 100 ms link no exported jog row outlives the arm's motion.

The arm is the real safety layer (``MemoryArm``: the jog deadman thread and
its stop, which it timestamps), jogged in real time as the robot node jogs
it: each jog reaches it 100 ms after the operator sent it, carrying that
send time (on the robot's clock) for the deadline. The recording is written
as the node writes it (``robot/command`` after the jog returned, with
``sent_velocity`` and ``t_sent_ns``); it is synthetic only in skipping the
link and the node, whose timing tests/robot covers.
"""

from __future__ import annotations

import time

import numpy as np
import pyarrow.parquet as pq
from synthetic import MS, POSE, robot_recording

from common.clock import now_ns
from deploy.export.cli import export
from deploy.export.resample import ExportConfig
from robot_side.arm.memory import MemoryArm, MemoryArmConfig

LINK_MS = 100
FPS = 100


def test_no_exported_jog_row_outlives_the_arm_on_a_100_ms_link(tmp_path):
    arm = MemoryArm(MemoryArmConfig(start_pose=tuple(POSE)))
    arm.connect()
    velocity = [0.02, 0.0, 0.0, 0.0, 0.0, 0.0]
    commands = []  # (record time, send time, velocity sent): the node's robot/command records
    try:
        for _burst in range(3):  # the operator holds a jog key 0.4 s, then lets go for 0.6 s
            end = time.monotonic() + 0.4
            while time.monotonic() < end:
                sent_ns = now_ns() - LINK_MS * MS
                sent = arm.jog(velocity, sent_ns / 1e9)
                commands.append((now_ns(), sent_ns, sent))
                time.sleep(0.033)
            time.sleep(0.6)
    finally:
        arm.disconnect()
    stops = np.array(arm.stop_times_ns)
    t0 = commands[0][0] - 500 * MS
    t_end = commands[-1][0] + 800 * MS
    pending = list(commands)

    def add_commands(rec, t):
        while pending and pending[0][0] <= t:
            t_rec, t_sent, sent = pending.pop(0)
            rec.write(
                "robot/command",
                t_rec,
                {
                    "seq": 1,
                    "action": "arm_jog",
                    "grip_level": None,
                    "velocity": velocity,
                    "sent_velocity": [float(v) for v in sent],
                    "t_sent_ns": t_sent,
                    "outcome": "applied",
                },
            )

    path = tmp_path / "robot.mcap"
    robot_recording(path, (t_end - t0) / 1e9, t0_ns=t0, extra=add_commands)
    out = tmp_path / "ds"
    export([path], out, ExportConfig(fps=FPS, episodes="session"))
    ep = pq.read_table(out / "meta/episodes/chunk-000/file-000.parquet").to_pylist()[0]
    rows = pq.read_table(out / "data/chunk-000/file-000.parquet").to_pydict()
    t_rows = ep["deepxpalm/t_first_ns"] + np.round(np.arange(ep["length"]) * 1e9 / FPS)
    jogging = np.array([any(a[:6]) for a in rows["action"]])
    assert jogging.sum() > 0.3 * 3 * 0.4 * FPS  # most of the time the key was held
    late = []
    for t in t_rows[jogging]:
        last_jog = max(c[0] for c in commands if c[0] <= t)
        stopped = stops[(stops > last_jog) & (stops <= t)]
        if stopped.size:
            late.append((t - stopped[0]) / 1e6)
    assert not late, (
        f"{len(late)} of {jogging.sum()} jog rows come after the arm's deadman had stopped it, "
        f"up to {max(late):.0f} ms after"
    )
