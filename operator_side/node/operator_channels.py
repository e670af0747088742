"""Everything the operator node records, in one place (channels: common/recording/channels.py).

A received stimulus and a sent command are recorded as the bytes on the
wire (a replay decodes exactly what crossed the link, signature included);
servo goals as written to the bus; the link's state with each heartbeat out;
the operator's episode marks. A node with no recorder records nothing.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from common.clocks.clock_sync import ClockSync
from common.recording.channels import NullRecorder, Recorder
from common.recording.episode_marks import CHANNEL as MARKS
from common.recording.episode_marks import check_mark
from operator_side.servos.calibration import LinkGlideCalibration


class OperatorChannels:
    """The operator node's channels; each call writes nothing when not recording."""

    def __init__(self, recorder: Recorder | None, now: Callable[[], int]) -> None:
        self.recorder = recorder or NullRecorder()
        self.on = not isinstance(self.recorder, NullRecorder)
        self.now = now

    def stimulus(self, seq: int, t_recv: int, wire: bytes) -> None:
        if self.on:
            self.recorder.write("operator/stimulus", t_recv, {"seq": seq, "wire": wire})

    def command(self, seq: int, t_send: int, wire: bytes) -> None:
        if self.on:
            self.recorder.write("operator/command", t_send, {"seq": seq, "wire": wire})

    def servo_goals(self, calibration: LinkGlideCalibration, counts: list[int]) -> None:
        if not self.on:
            return
        written = np.array(counts, dtype=np.int64)
        self.recorder.write(
            "operator/servo_goals",
            self.now(),
            {
                "ids": calibration.ids,
                "counts": written,
                "angles": calibration.counts_to_angles(written),
            },
        )

    def link(self, state: str, clock: ClockSync, stats: Callable[[], dict[str, float]]) -> None:
        """The link's state and clock estimate, with the node's stats (read only if recording)."""
        if not self.on:
            return
        est = clock.estimate()
        self.recorder.write(
            "operator/link",
            self.now(),
            {
                "state": state,
                "clock_offset_ns": None if est is None else est.offset_ns,
                "clock_uncertainty_ns": None if est is None else est.uncertainty_ns,
                **stats(),
            },
        )

    def mark(self, kind: str, task: str | None, source: str) -> bool:
        """The operator's mark on the episode in progress (common/recording/episode_marks.py).

        ValueError for a mark that means nothing; False when not recording:
        the mark would be lost.
        """
        problem = check_mark(kind, task)
        if problem is not None:
            raise ValueError(problem)
        if not self.on:
            return False
        record: dict[str, Any] = {"kind": kind, "source": source}
        if task is not None:
            record["task"] = task.strip()
        self.recorder.write(MARKS, self.now(), record)
        return True
