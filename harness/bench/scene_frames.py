"""The demo scene's tactile frames in virtual time, as its sensor would make them.

Shared by the sections that drive the nodes (skipping, scale, node_cpu, through
``Context.demo_frames``); a module of its own so that the section interface
and the sections that use it do not import each other.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from common.devices.lifecycle import build_device
from common.tactile.contract import FRAME_SHAPE
from deploy.scene import load_scene
from harness.bench.fixtures import serial_sensor
from robot_side.tactile import KINDS as TACTILE_KINDS


def demo_frames(scene_name: str, cycles: float) -> tuple[list[np.ndarray], list[Any], float]:
    """The scene's scripted frames at the sensor rate, with their truth; and the rate.

    For a ``simulated_serial`` sensor (the demo's) the board simulator makes
    each scan exactly as it would on the pty, and the real driver parses and
    calibrates the bytes; for ``scripted``, the in-process sensor's frames
    are made as its thread makes them. Either way the frames are the scene's,
    in virtual time, with no thread and no wall clock.
    """
    scene = load_scene(scene_name)
    section = dict(scene.robot.tactile)
    kind = section.get("kind")
    device = build_device(TACTILE_KINDS, section, "robot.tactile")  # never connected
    if kind == "simulated_serial":
        return _board_frames(device, cycles)
    if kind == "scripted":
        return _scripted_frames(device, cycles)
    raise ValueError(f"scene {scene_name}: tactile kind {kind!r} has no script to replay")


def _board_frames(device: Any, cycles: float) -> tuple[list[np.ndarray], list[Any], float]:
    """The board simulator's scans, made by its own code, read by the real driver.

    The simulator is never started (no pty, no thread): each scan is made by
    its scan routine while unplugged, which still records the scan's newtons
    and truth, and the bytes are encoded here from those newtons through the
    board's own calibration. Only the simulator's ADC noise (1 count, about
    0.003 N) is left out.
    """
    from common.tactile.synthetic import mirror_finger2
    from robot_side.tactile.wire import SEQ_MODULO, encode

    sim = device.simulator
    cfg = sim.config
    driver = serial_sensor()
    if device.sim_config.use_factory_calibration:
        driver.set_calibration(sim.calibration)
    n = round(cfg.script.duration_s * cycles * cfg.rate_hz)
    frames, truths = [], []
    for i in range(n):
        seq = (cfg.first_seq + i) % SEQ_MODULO
        sim.scan_at(i / cfg.rate_hz)
        newtons = sim.frame_for(seq)
        if newtons is None:
            raise RuntimeError("the board simulator kept no history of its scan")
        wire = mirror_finger2(np.asarray(newtons, dtype=np.float64))
        counts = np.clip(np.rint(sim.calibration.to_counts(wire)), 0, 0xFFFF).astype(np.uint16)
        driver.feed(encode(0, seq, counts[0]) + encode(1, seq, counts[1]), i)
        frames.append(driver.latest().frame)
        truths.append(sim.truth_for(seq))
    return frames, truths, cfg.rate_hz


def _scripted_frames(device: Any, cycles: float) -> tuple[list[np.ndarray], list[Any], float]:
    cfg = device.config
    model = device.model
    rng = np.random.default_rng(cfg.seed + 1)  # as ScriptedTactileSensor._run
    zero = np.zeros(FRAME_SHAPE, np.float32)
    if cfg.tare_frames > 0:
        zero = np.mean([model.frame(None, 1, rng) for _ in range(cfg.tare_frames)], axis=0).astype(
            np.float32
        )
    n = round(cfg.script.duration_s * cycles * cfg.rate_hz)
    frames, truths = [], []
    for i in range(n):
        truth = cfg.script.truth_at(i / cfg.rate_hz)
        frame = model.frame(truth.pattern, truth.grip_level or 1, rng) - zero
        frame[frame < cfg.generator.floor_n] = 0.0
        frames.append(frame)
        truths.append(truth)
    return frames, truths, cfg.rate_hz
