"""A scan's count bytes into a frame in newtons, in the common view (compiled where it can be)."""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from robot_side.tactile.board_calibration import WIRE_SHAPE, BoardCalibration
from robot_side.tactile.serial_config import SerialTactileConfig
from robot_side.tactile.wire import counts_of

log = logging.getLogger(__name__)


class ScanConverter:
    """Count bytes of one scan -> a ``FRAME_SHAPE`` float32 frame in newtons, common view.

    newtons = (counts - zero) * gain per taxel, above saturation clipped,
    below the floor 0; finger 2's columns reversed. The calibration arrays
    are put in the common view once, so the mirror is one gather of counts.
    Float32 throughout: counts are exact in it, and the rounding (about
    1e-5 N) is far below the ADC's step; one dtype means one conversion less
    per frame. With numba installed the conversion is one compiled call
    (``compiled.convert_scan``, bit-identical); ``numpy_path`` is the reference.
    """

    def __init__(self, calibration: BoardCalibration, config: SerialTactileConfig) -> None:
        self.calibration = calibration
        index = np.arange(np.prod(WIRE_SHAPE)).reshape(WIRE_SHAPE)
        if config.mirror_finger2:
            index[1] = index[1, :, ::-1]
        self._index = index.reshape(-1).astype(np.intp)
        self._order = None if not config.mirror_finger2 else self._index
        self._zero = calibration.zero_counts.reshape(-1)[self._index].astype(np.float32)
        self._gain = calibration.gain_n_per_count.reshape(-1)[self._index].astype(np.float32)
        self._floor = np.float32(config.floor_n)
        self._saturation = np.float32(config.saturation_n)
        self._compiled = compiled_converter()
        if self._compiled is not None:  # compile (or load the cache) now, not on a frame
            self(bytes(2 * self._index.size))

    def __call__(self, payloads: bytes) -> np.ndarray:
        if self._compiled is not None:
            if len(payloads) != 2 * self._index.size:  # compiled code does not bounds-check
                raise ValueError(
                    f"a scan is {2 * self._index.size} count bytes, not {len(payloads)}"
                )
            return self._compiled(
                payloads, self._index, self._zero, self._gain, self._floor, self._saturation
            )
        return self.numpy_path(payloads)

    def numpy_path(self, payloads: bytes) -> np.ndarray:
        counts = counts_of(payloads)
        if self._order is not None:
            counts = counts.take(self._order)
        newtons = (counts - self._zero) * self._gain
        np.minimum(newtons, self._saturation, out=newtons)
        newtons[newtons < self._floor] = 0.0
        return newtons.reshape(WIRE_SHAPE)


def compiled_converter() -> Any:
    try:
        from robot_side.tactile.compiled import convert_scan
    except ImportError:  # numba is in the robot extra; NumPy does the same, slower
        return None
    except Exception as e:  # a broken numba install must not stop the sensor
        log.warning("compiled tactile conversion unavailable (%s); using NumPy", e)
        return None
    return convert_scan
