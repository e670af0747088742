"""What every tactile source shares: newest frame first, newtons on demand, a pollable wake-up."""

from __future__ import annotations

import select

import numpy as np

from robot_side.tactile.base import TactileSample, TactileSensor


class Source(TactileSensor):
    """Publishes when told to, as a reader thread would."""

    def __init__(self) -> None:
        super().__init__()
        self.converted: list[int] = []

    @property
    def is_connected(self) -> bool:
        return True

    def connect(self) -> None: ...

    def disconnect(self) -> None: ...

    def stats(self) -> dict[str, int]:
        return {}

    def send(self, seq: int) -> None:
        self._publish_raw(seq, seq * 1000, seq, self._convert)

    def _convert(self, raw: int) -> np.ndarray:
        self.converted.append(raw)
        return np.full((2, 10, 10), float(raw), np.float32)


def _readable(fd: int) -> bool:
    return bool(select.select([fd], [], [], 0)[0])


def test_frames_nobody_takes_are_never_converted() -> None:
    src = Source()
    for seq in range(1, 6):
        src.send(seq)
    sample = src.latest()
    assert isinstance(sample, TactileSample) and sample.seq == 5
    assert sample.frame[0, 0, 0] == 5.0
    assert src.latest() is sample  # converted once, then kept
    assert src.converted == [5]


def test_the_frame_fd_wakes_only_for_the_frame_asked_for() -> None:
    src = Source()
    fd = src.frame_fd()
    src.send(1)
    assert src.take_newer(0).seq == 1
    assert not _readable(fd)
    assert src.take_newer(2) is None  # wants seq 3 or later
    src.send(2)  # skipped: no wake-up
    assert not _readable(fd)
    src.send(3)
    assert _readable(fd)
    assert src.take_newer(2).seq == 3
    assert not _readable(fd)  # taking it clears the wake-up
    src.send(4)  # nobody asked since: no wake-up
    assert not _readable(fd)
    assert src.converted == [1, 3]


def test_taking_without_a_frame_fd_never_breaks_publishing() -> None:
    src = Source()
    assert src.take_newer(0) is None  # no frame_fd() was ever made
    src.send(1)  # must not fail in the publishing (reader) thread
    assert src.take_newer(0).seq == 1
