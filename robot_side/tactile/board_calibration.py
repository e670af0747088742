"""Per-taxel calibration of the tactile board: raw ADC counts to newtons.

newtons = (counts - zero_counts) * gain_n_per_count, per taxel, in the pad's
OWN view (the order taxels arrive on the wire, finger 2 not mirrored): a
calibration belongs to a physical taxel, not to where the common view puts
it. The zero is re-captured with nothing grasped (it drifts with temperature
and mounting); the gain comes from loading taxels with known weights, once.

Stored as TOML so a lab can read and diff it: ``[pad0]`` and ``[pad1]``, each
with ``zero_counts`` and ``gain_n_per_count`` as a number (every taxel) or a
10 x 10 array of rows.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from common.config.typed import load_toml
from common.errors import ConfigError
from robot_side.tactile.wire import COLS, N_PADS, ROWS

WIRE_SHAPE = (N_PADS, ROWS, COLS)


@dataclass
class BoardCalibration:
    """Arrays of shape ``FRAME_SHAPE``, float64, in the pads' own (wire) view."""

    zero_counts: np.ndarray
    gain_n_per_count: np.ndarray

    def __post_init__(self) -> None:
        self.zero_counts = _as_taxels(self.zero_counts, "zero_counts")
        self.gain_n_per_count = _as_taxels(self.gain_n_per_count, "gain_n_per_count")
        if np.any(self.gain_n_per_count <= 0):
            raise ConfigError("tactile calibration: every gain_n_per_count must be positive")

    @classmethod
    def uniform(cls, zero_counts: float, gain_n_per_count: float) -> BoardCalibration:
        return cls(np.full(WIRE_SHAPE, zero_counts), np.full(WIRE_SHAPE, gain_n_per_count))

    def to_counts(self, newtons: np.ndarray) -> np.ndarray:
        """For simulators: newtons -> counts (float64, not rounded).

        The other direction, with floor, saturation and the mirror, is the
        serial driver's ``ScanConverter`` (one place, on its hot path).
        """
        return np.asarray(newtons, dtype=np.float64) / self.gain_n_per_count + self.zero_counts


def _as_taxels(value: object, name: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 0:
        arr = np.full(WIRE_SHAPE, float(arr))
    if arr.shape != WIRE_SHAPE:
        raise ConfigError(
            f"tactile calibration: {name} must have shape {WIRE_SHAPE}, not {arr.shape}"
        )
    if not np.all(np.isfinite(arr)):
        raise ConfigError(f"tactile calibration: {name} has non-finite values")
    return arr.copy()


def load_board_calibration(path: str | Path) -> BoardCalibration:
    data = load_toml(path)
    unknown = set(data) - {f"pad{p}" for p in range(N_PADS)}
    if unknown:
        raise ConfigError(f"{path}: unknown table(s) {sorted(unknown)}; expected [pad0] and [pad1]")
    zero = np.zeros(WIRE_SHAPE)
    gain = np.zeros(WIRE_SHAPE)
    for p in range(N_PADS):
        table = data.get(f"pad{p}")
        if not isinstance(table, dict):
            raise ConfigError(f"{path}: missing table [pad{p}]")
        extra = set(table) - {"zero_counts", "gain_n_per_count"}
        if extra or len(table) != 2:
            raise ConfigError(
                f"{path}: [pad{p}] needs exactly zero_counts and gain_n_per_count, "
                f"got {sorted(table)}"
            )
        for key, out in (("zero_counts", zero), ("gain_n_per_count", gain)):
            try:
                arr = np.asarray(table[key], dtype=np.float64)
            except (TypeError, ValueError):
                raise ConfigError(
                    f"{path}: [pad{p}].{key} must be a number or 10 x 10 array"
                ) from None
            if arr.ndim == 0:
                out[p] = float(arr)
            elif arr.shape == (ROWS, COLS):
                out[p] = arr
            else:
                raise ConfigError(
                    f"{path}: [pad{p}].{key} must be a number or {ROWS} x {COLS}, not {arr.shape}"
                )
    try:
        return BoardCalibration(zero, gain)
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from None


def save_board_calibration(cal: BoardCalibration, path: str | Path) -> None:
    lines = [
        "# Tactile board calibration: newtons = (counts - zero_counts) * gain_n_per_count.",
        "# Per taxel, in each pad's own wire view (finger 2 NOT mirrored); rows from the",
        "# fingertip end. Re-capture zero_counts with nothing grasped.",
    ]
    for p in range(N_PADS):
        lines.append(f"\n[pad{p}]")
        for key, arr, fmt in (
            ("zero_counts", cal.zero_counts[p], "{:.2f}"),
            ("gain_n_per_count", cal.gain_n_per_count[p], "{:.6g}"),
        ):
            rows = ",\n".join("  [" + ", ".join(fmt.format(v) for v in row) + "]" for row in arr)
            lines.append(f"{key} = [\n{rows},\n]")
    Path(path).write_text("\n".join(lines) + "\n")
