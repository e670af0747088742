"""Scripted grasps: what a simulated sensor shows, and when.

A script is a list of grasps; each ramps the grip up to its level, holds,
releases and pauses with nothing grasped. Simulators (the in-process
scripted sensor and the serial-board simulator) look up the ground truth at
a time since start, so the same script gives the same scene on any wire.
"""

from __future__ import annotations

from dataclasses import dataclass

from common.config.typed import param
from common.errors import ConfigError
from common.tactile.contract import N_GRIP_LEVELS, N_PATTERNS
from robot_side.tactile.base import GraspTruth


@dataclass
class GraspStep:
    pattern: int = param(0, "0..11: 3 * angle class + position class")
    grip_level: int = param(20, "1..31: the level the grip ramps up to and holds")
    ramp_s: float = param(0.4, "time to close from level 1 to grip_level")
    hold_s: float = param(1.2, "time held at grip_level")
    release_s: float = param(0.2, "time to open back to level 1")
    pause_s: float = param(0.4, "time with nothing grasped afterwards")

    def __post_init__(self) -> None:
        if not 0 <= self.pattern < N_PATTERNS:
            raise ConfigError(f"grasp pattern {self.pattern} is not in 0..{N_PATTERNS - 1}")
        if not 1 <= self.grip_level <= N_GRIP_LEVELS:
            raise ConfigError(f"grasp grip_level {self.grip_level} is not in 1..{N_GRIP_LEVELS}")
        for name in ("ramp_s", "hold_s", "release_s", "pause_s"):
            if getattr(self, name) < 0:
                raise ConfigError(f"grasp {name} must not be negative")

    @property
    def duration_s(self) -> float:
        return self.ramp_s + self.hold_s + self.release_s + self.pause_s

    def truth_at(self, t: float) -> GraspTruth:
        """Ground truth ``t`` seconds into this grasp."""
        if t < self.ramp_s:
            level = 1 + (self.grip_level - 1) * t / self.ramp_s
        elif t < self.ramp_s + self.hold_s:
            level = self.grip_level
        elif t < self.ramp_s + self.hold_s + self.release_s:
            level = self.grip_level - (self.grip_level - 1) * (
                (t - self.ramp_s - self.hold_s) / self.release_s
            )
        else:
            return GraspTruth(pattern=None, grip_level=None)
        return GraspTruth(pattern=self.pattern, grip_level=max(1, round(level)))


def _every_pattern() -> list[GraspStep]:
    return [GraspStep(pattern=p) for p in range(N_PATTERNS)]


@dataclass
class GraspScript:
    grasps: list[GraspStep] = param(_every_pattern(), "the grasps, in order")
    loop: bool = param(True, "start again after the last grasp")
    start_delay_s: float = param(0.5, "nothing grasped for this long at start (sensor zeroing)")

    def __post_init__(self) -> None:
        if not self.grasps:
            raise ConfigError("a grasp script needs at least one grasp")
        self._total = sum(g.duration_s for g in self.grasps)
        if self._total <= 0:
            raise ConfigError("a grasp script must last longer than zero seconds")

    @property
    def duration_s(self) -> float:
        return self.start_delay_s + self._total

    def truth_at(self, t: float) -> GraspTruth:
        """Ground truth ``t`` seconds after the script started."""
        t -= self.start_delay_s
        if t < 0:
            return GraspTruth(pattern=None, grip_level=None)
        if self.loop:
            t %= self._total
        for grasp in self.grasps:
            if t < grasp.duration_s:
                return grasp.truth_at(t)
            t -= grasp.duration_s
        return GraspTruth(pattern=None, grip_level=None)
