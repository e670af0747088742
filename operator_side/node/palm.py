"""The palm: the stimulus to render, the LinkGlide's servo goals, and the latency to them.

A stimulus is rendered only while fresh: one older than ``stale_after_ms``
(capture time mapped through the estimated clock offset) lifts every linkage
off the palm, and rendering resumes by itself when fresh data does. The
goals step toward their target at the renderer's rate limit on every palm
step; IK runs only when the stimulus rendered changes. On the way out the
palm goes straight to the retract pose, torque on until it is there.
"""

from __future__ import annotations

import collections
import logging
from collections import Counter
from collections.abc import Callable

import numpy as np

from common.errors import DeviceError
from operator_side.node.arrivals import Arrivals
from operator_side.node.config import OperatorConfig
from operator_side.node.operator_channels import OperatorChannels
from operator_side.palm.renderer import LinkGlideRenderer
from operator_side.servos.base import ServoBus
from operator_side.servos.calibration import LinkGlideCalibration

log = logging.getLogger(__name__)

#: the clean stop's longest wait for the retract pose before torque off (a pressing linkage
#: is a few degrees from it: about 0.1 s at the servos' speed)
LIFT_ARRIVAL_S = 0.2


class Palm:
    """The renderer and the servo bus, driven from the stimulus ``Arrivals`` holds."""

    def __init__(
        self,
        config: OperatorConfig,
        servos: ServoBus,
        calibration: LinkGlideCalibration,
        arrivals: Arrivals,
        *,
        counters: Counter[str],
        now: Callable[[], int],
        recording: OperatorChannels,
    ) -> None:
        self.config = config
        self.servos = servos
        self.arrivals = arrivals
        self.counters = counters
        self.now = now
        self.recording = recording
        self.use_calibration(calibration)
        self.latencies_ms: collections.deque[float] = collections.deque(
            maxlen=config.latency_window
        )
        self.link_state = "down"
        #: (monotonic ns, new state) of the latest link state changes
        self.link_changes: collections.deque[tuple[int, str]] = collections.deque(maxlen=256)
        self.goal: list[int] = self.renderer.retract_goals  # six counts, ids 1..6
        self._goal_key: int | None = None  # stimulus seq the goal was computed for
        #: the goals last sent to the bus (None before the first write)
        self.written: list[int] | None = None
        self._last_step_ns = 0
        self._latency_cache: tuple[int, dict[str, float]] = (0, {})

    def use_calibration(self, calibration: LinkGlideCalibration) -> None:
        self.calibration = calibration
        self.renderer = LinkGlideRenderer(self.config.renderer, calibration)
        self._servo_ids = [int(i) for i in calibration.ids]

    def fresh_stimulus(self, now: int) -> tuple[np.ndarray | None, float | None]:
        """(the stimulus to render, or None when stale or none; its age in ms, if any)."""
        arrivals = self.arrivals
        stim, captured = arrivals.stimulus, arrivals.local_capture_ns
        if stim is None or captured is None:
            return None, None
        age_ms = (now - captured) / 1e6
        if age_ms > self.config.link.stale_after_ms:
            return None, age_ms
        return stim.stimulus, age_ms

    def palm_step(self, now: int, period_ns: int) -> None:
        stimulus, age_ms = self.fresh_stimulus(now)
        stim = self.arrivals.stimulus
        state = "ok" if stimulus is not None else ("stale" if stim is not None else "down")
        if state != self.link_state:
            log.info(
                "link %s -> %s (age %s ms)",
                self.link_state,
                state,
                "n/a" if age_ms is None else f"{age_ms:.0f}",
            )
            if self.link_state == "ok":  # the palm left a fresh stimulus (a first one read
                self.counters["lift_offs"] += 1  # stale never put it on: no lift-off)
            self.link_state = state
            self.link_changes.append((now, state))
        key = stim.seq if stimulus is not None else None
        if key != self._goal_key:  # IK only when what is rendered changed
            self.goal = self.renderer.goals_for(stimulus)
            self._goal_key = key
            self.counters["targets_computed"] += 1
        fraction = 1.0 if not self._last_step_ns else (now - self._last_step_ns) / period_ns
        current = self.written if self.written is not None else self.renderer.retract_goals
        nxt = self.renderer.step_goals(current, self.goal, fraction)
        self._last_step_ns = now
        # a stimulus that moved nothing has no latency
        captured = self.arrivals.take_latency_capture()
        if nxt != self.written:
            self.write(nxt)
            if captured is not None and stimulus is not None:
                self.latencies_ms.append((self.now() - captured) / 1e6)
                self.counters["latency_samples"] += 1

    def next_step_ns(self, now: int, period: int) -> int:
        """When the next palm step is needed if no message arrives first."""
        if self.written is not None and self.written != self.goal:
            return now + period  # still stepping toward the goal
        captured = self.arrivals.local_capture_ns
        if self.link_state == "ok" and captured is not None:
            return captured + round(self.config.link.stale_after_ms * 1e6) + 1
        return now + 10 * period  # lifted and idle: messages wake the loop

    def write(self, counts: list[int]) -> None:
        self.servos.write_goals(dict(zip(self._servo_ids, counts, strict=True)))
        self.written = counts
        self.recording.servo_goals(self.calibration, counts)
        self.counters["servo_writes"] += 1

    def lift_off_now(self) -> None:
        """On shutdown: straight to the retract pose (a lift is always safe), and torque stays
        on until the servos are there (at most ``LIFT_ARRIVAL_S``): let go mid-way, a linkage
        stays where it was, maybe on the palm."""
        self.write(self.renderer.retract_goals)
        goals = dict(zip(self._servo_ids, self.renderer.retract_goals, strict=True))
        try:
            away = self.servos.wait_for_arrival(goals, LIFT_ARRIVAL_S)
        except DeviceError as e:  # the bus failed on the way out: torque goes off regardless
            log.warning("lift on the way out: positions unreadable (%s); torque off", e)
            return
        if away:
            log.warning(
                "lift on the way out: servos %s not at the retract pose after %.0f ms (at %s); "
                "torque off",
                sorted(away),
                LIFT_ARRIVAL_S * 1e3,
                away,
            )

    def goal_counts(self) -> np.ndarray:
        """The goals last written (the retract pose before the first write)."""
        written = self.written if self.written is not None else self.renderer.retract_goals
        return np.array(written, np.int64)

    def latency_summary(self) -> dict[str, float]:
        """Percentiles over the window, recomputed only when a sample was added."""
        n = self.counters["latency_samples"]
        if self._latency_cache[0] != n and self.latencies_ms:
            lat = np.fromiter(self.latencies_ms, dtype=np.float64)
            p50, p99, p999 = np.percentile(lat, (50, 99, 99.9))
            self._latency_cache = (
                n,
                {
                    "latency_p50_ms": float(p50),
                    "latency_p99_ms": float(p99),
                    "latency_p999_ms": float(p999),
                    "latency_max_ms": float(lat.max()),
                    "latency_last_ms": float(lat[-1]),
                },
            )
        return self._latency_cache[1]
