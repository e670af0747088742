"""In-process simulated tactile sensor: scripted grasps, synthetic frames, no wire.

The quickest way to run the whole loop. Frames come from the synthetic
pad model at the sensor's rate, on a background thread paced against the
monotonic clock, each with its ground truth attached. The serial-board
simulator shows the same scenes through the real driver and wire.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass

import numpy as np

from common.clocks.clock import Rate, now_ns
from common.config.typed import param
from common.errors import DeviceAlreadyConnectedError
from common.tactile.contract import FRAME_SHAPE
from common.tactile.synthetic import GeneratorParams, HeldGrasp, SyntheticTactileModel
from robot_side.tactile.base import TactileSample, TactileSensor
from robot_side.tactile.script import GraspScript

log = logging.getLogger(__name__)


@dataclass
class ScriptedTactileConfig:
    rate_hz: float = param(120.0, "frames per second, as the real sensor board")
    seed: int = param(0, "seeds the pad defects and the grasp-to-grasp variation")
    script: GraspScript = param(GraspScript(), "the grasps to show")
    generator: GeneratorParams = param(GeneratorParams(), "the synthetic pad model")
    tare_frames: int = param(
        24,
        "frames with nothing grasped averaged at connect and subtracted, as the serial "
        "driver's zeroing does (removes stuck taxels); 0 = no tare",
    )


class ScriptedTactileSensor(TactileSensor):
    Config = ScriptedTactileConfig
    simulated = True

    def __init__(self, config: ScriptedTactileConfig | None = None) -> None:
        super().__init__()
        self.config = config or ScriptedTactileConfig()
        self._model = SyntheticTactileModel(self.config.generator, seed=self.config.seed)
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._frames = 0

    @property
    def model(self) -> SyntheticTactileModel:
        """The pad model the frames come from (the bench replays the script through it)."""
        return self._model

    @property
    def is_connected(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def connect(self) -> None:
        if self._thread is not None:
            raise DeviceAlreadyConnectedError("scripted tactile sensor is already connected")
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="scripted-tactile", daemon=True)
        self._thread.start()

    def disconnect(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._thread = None

    def _run(self) -> None:
        rng = np.random.default_rng(self.config.seed + 1)
        floor = self.config.generator.floor_n
        zero = np.zeros(FRAME_SHAPE, np.float32)
        if self.config.tare_frames > 0:
            zero = np.mean(
                [self._model.frame(None, 1, rng) for _ in range(self.config.tare_frames)], axis=0
            ).astype(np.float32)
        held = HeldGrasp(self._model, rng)
        script = self.config.script
        rate = Rate(self.config.rate_hz)
        t0 = now_ns()
        seq = 0
        while not self._stop.is_set():
            truth = script.truth_at((now_ns() - t0) / 1e9)
            frame = held.frame(truth.pattern, truth.grip_level) - zero
            frame[frame < floor] = 0.0  # the floor applies after zeroing, as on the board
            seq += 1
            self._publish(TactileSample(frame=frame, seq=seq, t_capture_ns=now_ns(), truth=truth))
            self._frames = seq
            rate.sleep()

    def stats(self) -> dict[str, int]:
        return {"frames": self._frames, "dropped": 0}
