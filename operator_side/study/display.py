"""The study's palm display: a pattern's stimulus rendered on LinkGlide, real or simulated.

The study runs without a robot: it makes each trial's stimulus itself, as the
robot would have, and renders it through the node's own ``LinkGlideRenderer``
(same contact mapping, kinematics, calibration clip and rate limit), so a
participant feels exactly what an operator would.

A stimulus source per trial:

- ``direct``: a simulated grasp of the pattern on the pads, downsized and
  peaked but not masked (the paper's Table I condition);
- ``masked``: the same, masked with the true pattern (Table II, with a
  classifier that is never wrong);
- ``ideal``: exactly the mask's cells at a fixed force (no sensor at all).

``direct`` and ``masked`` draw fresh sensor noise at ``frame_rate_hz``, as a
live grasp would. The pad model and the rendering are the robot's own
(``common.tactile.synthetic``, ``common.tactile.stimulus``): NumPy only, shared
through ``common`` so the study never imports the robot side.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

import numpy as np

from common.clocks.clock import Rate, now_ns
from common.errors import DeviceError
from common.tactile.contract import MASKS
from common.tactile.stimulus import render_stimulus
from common.tactile.synthetic import SyntheticTactileModel
from operator_side.palm.renderer import LinkGlideRenderer, RendererConfig
from operator_side.servos.base import ServoBus
from operator_side.servos.calibration import LinkGlideCalibration
from operator_side.study.protocol import StudyConfig

log = logging.getLogger(__name__)

StimulusSource = Callable[[], np.ndarray]


class StimulusMaker:
    """Makes each trial's stimulus source for the configured mode."""

    def __init__(self, config: StudyConfig) -> None:
        self.config = config
        self._model = None
        if config.mode in ("direct", "masked"):
            self._model = SyntheticTactileModel(seed=config.sensor_seed)

    def source(self, pattern: int, rng: np.random.Generator) -> tuple[StimulusSource, int]:
        """(source, grip level) for one trial; the grasp is held for the whole trial."""
        cfg = self.config
        grip = int(rng.integers(cfg.grip_level_min, cfg.grip_level_max + 1))
        if cfg.mode == "ideal":
            stim = (MASKS[pattern] * np.float32(cfg.ideal_force_n)).astype(np.float32)
            return (lambda: stim), grip
        model = self._model
        grasp = model.draw_grasp(pattern, rng)
        mask = pattern if cfg.mode == "masked" else None

        def next_stimulus() -> np.ndarray:
            return render_stimulus(model.grasp_frame(grasp, grip, rng), mask)

        return next_stimulus, grip


class PalmDisplay:
    """Renders the current stimulus source on the servos at the palm step rate, in a thread.

    ``show`` swaps the source and returns the onset: the monotonic time (ns)
    of the first servo write toward it, which is when response times start.
    ``lift`` retracts every linkage. A failing bus stops the thread; the
    next ``show`` or ``lift`` raises ``DeviceError`` with the cause.
    """

    def __init__(
        self,
        servos: ServoBus,
        renderer: RendererConfig,
        *,
        frame_rate_hz: float = 30.0,
        calibration: LinkGlideCalibration | None = None,
    ) -> None:
        self.servos = servos
        self.renderer_config = renderer
        self.frame_period_ns = round(1e9 / frame_rate_hz)
        self._calibration = calibration
        self.renderer: LinkGlideRenderer | None = None
        self._lock = threading.Lock()
        self._source: StimulusSource | None = None
        self._generation = 0
        self._onset: dict[int, int] = {}
        self._written: np.ndarray | None = None
        self.current_stimulus: np.ndarray | None = None
        self.first_stimulus: np.ndarray | None = None
        self._changed = threading.Condition(self._lock)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None
        self.writes = 0

    # ----------------------------------------------------------- lifecycle
    def connect(self) -> None:
        if not self.servos.is_connected:
            self.servos.connect()
        calibration = (
            getattr(self.servos, "calibration", None) or self._calibration or LinkGlideCalibration()
        )
        self.renderer = LinkGlideRenderer(self.renderer_config, calibration)
        self.calibration = calibration
        self.servos.set_torque(True)
        self._write(self.renderer.retract_counts)
        self._thread = threading.Thread(target=self._run, name="study-display", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Lift every linkage straight away (always safe), stop, disconnect."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None
        try:
            if self.servos.is_connected and self.renderer is not None:
                self._write(self.renderer.retract_counts)
        finally:
            self.servos.disconnect()

    def __enter__(self) -> PalmDisplay:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------- control
    def show(self, source: StimulusSource | None, timeout_s: float = 2.0) -> int:
        """Render ``source`` from now on (None lifts); the onset time in ns."""
        self._raise_if_failed()
        with self._changed:
            self._generation += 1
            gen = self._generation
            self._source = source
            self.first_stimulus = None
            ok = self._changed.wait_for(
                lambda: gen in self._onset or self.error is not None, timeout_s
            )
            self._raise_if_failed()
            if not ok:
                raise DeviceError(
                    f"the LinkGlide display did not start a stimulus in {timeout_s} s"
                )
            return self._onset.pop(gen)

    def lift(self) -> int:
        return self.show(None)

    def _raise_if_failed(self) -> None:
        if self.error is not None:
            raise DeviceError(f"LinkGlide display stopped: {self.error!r}") from self.error

    def _run(self) -> None:
        assert self.renderer is not None
        rate = Rate(self.renderer_config.palm_step_rate_hz)
        seen_gen, next_frame, stimulus = -1, 0, None
        try:
            while not self._stop.is_set():
                with self._lock:
                    gen, source = self._generation, self._source
                now = now_ns()
                if gen != seen_gen or (source is not None and now >= next_frame):
                    stimulus = None if source is None else np.asarray(source(), np.float32)
                    next_frame = now + self.frame_period_ns
                goal = self.renderer.target_counts(stimulus)
                current = self._written if self._written is not None else goal
                nxt = self.renderer.step(current, goal)
                if self._written is None or not np.array_equal(nxt, self._written):
                    self._write(nxt)
                if gen != seen_gen:
                    # The onset is this cycle's write (or now, if the goal was already there).
                    with self._changed:
                        self._onset[gen] = now_ns()
                        self.current_stimulus = stimulus
                        self.first_stimulus = stimulus
                        self._changed.notify_all()
                    seen_gen = gen
                else:
                    self.current_stimulus = stimulus
                rate.sleep()
        except BaseException as e:  # surfaced by the next show()/lift()
            log.exception("LinkGlide display failed; lifting off")
            try:
                self._write(self.renderer.retract_counts)
            except Exception:
                log.exception("could not lift off either")
            with self._changed:
                self.error = e
                self._changed.notify_all()

    def _write(self, counts: np.ndarray) -> None:
        goals = {int(i): int(c) for i, c in zip(self.calibration.ids, counts, strict=True)}
        self.servos.write_goals(goals)
        self._written = np.array(counts, dtype=np.int64)
        self.writes += 1


def wait_s(seconds: float, stop: threading.Event | None = None) -> None:
    """A pause the runner can cut short on shutdown."""
    if seconds <= 0:
        return
    if stop is None:
        time.sleep(seconds)
    else:
        stop.wait(seconds)
