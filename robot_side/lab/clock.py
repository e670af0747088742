"""How fast the world's simulated time runs against the wall: its sim/wall ratio.

The arm simulator and the physics share the world's simulated time (the
physics loop advances the arm by the time it steps), so a world that falls
behind slows everything alike; but a robot node, an operator and a link
simulator on the same machine run on the wall, and a trial measured while the
world was behind is not the trial a real robot would give. The meter says how
far behind, per window of wall time, so the world's stats, its log and the
task bench can report and flag it.
"""

from __future__ import annotations

from dataclasses import dataclass

#: sim/wall below this fell behind real time (a trial below it is flagged)
BEHIND_SIM_WALL = 0.98


@dataclass
class SimWallMeter:
    """sim/wall over consecutive windows of ``window_s`` wall seconds."""

    window_s: float = 1.0

    def __post_init__(self) -> None:
        self._start: tuple[float, float] | None = None
        #: the last complete window's sim/wall, None before the first one closes
        self.last: float | None = None
        #: the slowest complete window since :meth:`mark` (or the start)
        self.lowest: float | None = None
        #: complete windows since :meth:`mark` that fell behind (below ``BEHIND_SIM_WALL``)
        self.windows_behind = 0
        self.windows = 0

    def update(self, wall_s: float, sim_s: float) -> float | None:
        """Record the clocks now; the ratio of a window that just closed, else None."""
        if self._start is None:
            self._start = (wall_s, sim_s)
            return None
        w0, s0 = self._start
        if wall_s - w0 < self.window_s:
            return None
        ratio = (sim_s - s0) / (wall_s - w0)
        self._start = (wall_s, sim_s)
        self.last = ratio
        self.lowest = ratio if self.lowest is None else min(self.lowest, ratio)
        self.windows += 1
        self.windows_behind += ratio < BEHIND_SIM_WALL
        return ratio

    def mark(self) -> None:
        """Start counting the slowest window afresh (a new trial)."""
        self.lowest = None
        self.windows = 0
        self.windows_behind = 0


def sim_wall_between(before: dict, after: dict) -> float | None:
    """sim/wall between two of the world's ``stats()`` (a trial, a lift), None if no wall passed."""
    wall = after["wall_time_s"] - before["wall_time_s"]
    return (after["sim_time_s"] - before["sim_time_s"]) / wall if wall > 0 else None
