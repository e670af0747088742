"""An operator recording replayed: each stimulus rendered again, each servo write checked."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from common.config.typed import from_dict
from common.wire.codec import DecodeError, decode
from common.wire.messages import Stimulus
from deploy.replay.recorded import Report

log = logging.getLogger(__name__)


class OperatorReplay:
    """Stimuli -> LinkGlide goals; each recorded write must be one legal step toward them."""

    def __init__(self, config: Any, report: Report, calibration_file: Path | None = None) -> None:
        from operator_side.palm.renderer import LinkGlideRenderer

        self.calibration = calibration_for(config, calibration_file)
        self.renderer = LinkGlideRenderer(config.renderer, self.calibration)
        self.report = report
        self.target: np.ndarray | None = None  # goal counts of the newest stimulus
        self.prev: np.ndarray | None = None
        self.pending_jump: tuple[np.ndarray, np.ndarray] | None = None
        self.calibration_checked = False

    def feed(self, channel: str, record: dict[str, Any], t_ns: int = 0) -> None:
        if channel == "operator/stimulus":
            try:
                msg = decode(record["wire"])
            except (DecodeError, KeyError, TypeError) as e:
                self.report.mismatch("stimulus_wire", str(e))
                return
            if isinstance(msg, Stimulus):
                self.target = self.renderer.target_counts(msg.stimulus)
                self.report.ok("stimuli_rendered")
        elif channel == "operator/servo_goals":
            self._write(record)

    def _write(self, record: dict[str, Any]) -> None:
        counts = np.asarray(record["counts"])
        cal = self.calibration
        if counts.shape != (6,) or counts.dtype.kind not in "iu":
            self.report.mismatch("servo_goal", f"counts {counts!r} are not 6 integers")
            return
        if not cal.within_limits(counts):
            self.report.mismatch("servo_limits", f"counts {counts.tolist()} outside the limits")
        if not self.calibration_checked and record.get("angles") is not None:
            self.calibration_checked = True
            angles = np.asarray(record["angles"], dtype=np.float64)
            if not np.allclose(cal.counts_to_angles(counts), angles, atol=1e-9):
                log.warning(
                    "the recorded angles do not fit this calibration: pass --calibration FILE"
                )
                self.report.mismatch("calibration", "recorded angles do not fit the calibration")
        prev, self.prev = self.prev, counts
        if self.pending_jump is not None:  # a jump is legal only as the very last write
            self.report.mismatch("servo_step", f"jump {self.pending_jump[0].tolist()} -> ...")
            self.pending_jump = None
        retract = self.renderer.retract_counts
        if prev is None:
            if np.array_equal(counts, retract):
                self.report.ok("servo_writes_consistent")
            else:
                self.report.mismatch("servo_step", f"first write {counts.tolist()} is not lifted")
            return
        targets = [retract] if self.target is None else [self.target, retract]
        limit = self.renderer.max_step_counts
        if any(_is_step(prev, counts, t, limit) for t in targets):
            self.report.ok("servo_writes_consistent")
        elif np.array_equal(counts, retract):
            self.pending_jump = (prev, counts)  # the shutdown lift-off, if nothing follows
        else:
            self.report.mismatch(
                "servo_step",
                f"{prev.tolist()} -> {counts.tolist()} is no step of at most {limit} counts "
                f"toward {targets[0].tolist()} or the lifted pose",
            )

    def finish(self) -> None:
        if self.pending_jump is not None:
            self.report.ok("shutdown_lift_offs")


def _is_step(prev: np.ndarray, nxt: np.ndarray, target: np.ndarray, max_step: int) -> bool:
    """Whether ``nxt`` is ``renderer.step(prev, target, f)`` for some fraction f in (0, 1]."""
    delta = nxt.astype(np.int64) - prev
    need = target.astype(np.int64) - prev
    if np.any(np.abs(delta) > max_step) or np.any(delta * need < 0):
        return False
    if np.any(np.abs(delta) > np.abs(need)):
        return False
    clipped = np.abs(delta) < np.abs(need)
    if not clipped.any():
        return True
    step = np.abs(delta[clipped])
    return bool(np.all(step == step[0]) and np.all(np.abs(need[~clipped]) <= step[0]))


def calibration_for(config: Any, calibration_file: Path | None) -> Any:
    """The servo calibration an operator recording was made with, as far as it can be found."""
    from operator_side.servos.calibration import LinkGlideCalibration, load_calibration

    if calibration_file is not None:
        return load_calibration(calibration_file)
    servos = dict(config.servos)
    if servos.get("calibration_file"):
        path = Path(servos["calibration_file"])
        if path.exists():
            return load_calibration(path)
        log.warning("the recorded calibration file %s is not here; using the inline one", path)
    if "calibration" in servos:
        return from_dict(LinkGlideCalibration, servos["calibration"], where="servos.calibration")
    return LinkGlideCalibration()
