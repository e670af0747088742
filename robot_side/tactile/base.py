"""The tactile sensor interface every source implements.

Frames follow the project's tactile convention (docs/tactile.md): float32
newtons of shape ``FRAME_SHAPE``; axis 0 the pad (0 = finger 1, 1 = finger 2,
already mirrored into finger 1's view), axis 1 the row (0 at the fingertip
end), axis 2 the column (0 at the left).
"""

from __future__ import annotations

import abc
import contextlib
import os
import threading
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from common.clocks.clock import now_ns
from common.devices.lifecycle import Device
from common.errors import StaleDataError

_NEVER = 2**63 - 1  # a sequence number no frame reaches


@dataclass(frozen=True, slots=True)
class GraspTruth:
    """What a simulator knows it is showing; real sensors never have this."""

    pattern: int | None  # 0..11, None when nothing is grasped
    grip_level: int | None  # 1..31


@dataclass(frozen=True, slots=True)
class TactileSample:
    frame: np.ndarray  # FRAME_SHAPE float32 newtons, common view
    seq: int  # increases by one per frame the source produced (gaps = drops)
    t_capture_ns: int  # monotonic clock, when the frame was complete
    truth: GraspTruth | None = None


@dataclass(frozen=True, slots=True)
class _RawSample:
    """A frame not yet in newtons: converted only if somebody reads it."""

    seq: int
    t_capture_ns: int
    truth: GraspTruth | None
    convert: Callable[[Any], np.ndarray]
    raw: Any


class TactileSensor(Device):
    """A source of frames that keeps only the newest one (freshness first).

    Subclasses call ``_publish(sample)`` (or ``_publish_raw``) from their
    reader thread; callers use ``read_latest`` or ``wait_for_frame``.
    """

    family = "tactile sensor"

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._latest: TactileSample | _RawSample | None = None
        self._waiting_after = -1  # the seq the current waiter needs to exceed
        self._fd_after = _NEVER  # frame_fd turns readable for a frame newer than this
        self._fd_pair: tuple[int, int] | None = None

    def _publish(self, sample: TactileSample | _RawSample) -> None:
        with self._cond:
            self._latest = sample
            if sample.seq > self._waiting_after:  # wake a waiter only for what it waits for
                self._cond.notify_all()
            if sample.seq > self._fd_after:  # one byte per take_newer() that found nothing
                self._fd_after = _NEVER
                with contextlib.suppress(OSError):  # full or closed: readable already / gone
                    os.write(self._fd_pair[1], b"f")  # type: ignore[index]

    def _publish_raw(
        self,
        seq: int,
        t_capture_ns: int,
        raw: Any,
        convert: Callable[[Any], np.ndarray],
        truth: GraspTruth | None = None,
    ) -> None:
        """Publish a frame as read off the wire; ``convert(raw)`` makes its newtons.

        The conversion runs once, on the thread that takes the frame, and
        never for a frame that is superseded unread: a node rendering 60 of
        120 frames a second converts half of them.
        """
        self._publish(_RawSample(seq, t_capture_ns, truth, convert, raw))

    def _newest(self) -> TactileSample | None:
        """The newest frame in newtons; call with ``_cond`` held."""
        s = self._latest
        if type(s) is _RawSample:
            s = self._latest = TactileSample(s.convert(s.raw), s.seq, s.t_capture_ns, s.truth)
        return s  # type: ignore[return-value]

    def latest(self) -> TactileSample | None:
        with self._cond:
            return self._newest()

    def read_latest(self, max_age_ms: float) -> TactileSample:
        """The newest frame; ``StaleDataError`` when it is older than ``max_age_ms``."""
        self.require_connected()
        sample = self.latest()
        if sample is None:
            raise StaleDataError(f"{type(self).__name__}: no frame received yet")
        age_ms = (now_ns() - sample.t_capture_ns) / 1e6
        if age_ms > max_age_ms:
            raise StaleDataError(
                f"{type(self).__name__}: newest frame is {age_ms:.0f} ms old "
                f"(limit {max_age_ms:.0f} ms); is the sensor still streaming?"
            )
        return sample

    def frame_fd(self) -> int:
        """A file descriptor to poll beside sockets, for a loop that waits on both.

        It turns readable when a frame newer than the one the last
        ``take_newer`` call found missing arrives; frames nobody asked for
        never wake the loop.
        """
        with self._cond:
            if self._fd_pair is None:
                r, w = os.pipe()
                os.set_blocking(r, False)
                os.set_blocking(w, False)
                self._fd_pair = (r, w)
                weakref.finalize(self, _close_fds, r, w)
            return self._fd_pair[0]

    def take_newer(self, after_seq: int) -> TactileSample | None:
        """The newest frame if it is newer than ``after_seq``; else None, and ``frame_fd`` wakes.

        The poll-loop form of ``wait_for_frame``: call it, poll ``frame_fd``
        with the loop's sockets if it found nothing, and call it again.
        """
        self.require_connected()
        with self._cond:
            if self._fd_pair is not None:
                with contextlib.suppress(OSError):
                    os.read(self._fd_pair[0], 64)
            latest = self._latest
            if latest is not None and latest.seq > after_seq:
                self._fd_after = _NEVER
                return self._newest()
            if self._fd_pair is not None:  # without frame_fd() there is nothing to wake
                self._fd_after = after_seq
            return None

    def wait_for_frame(self, after_seq: int, timeout_s: float) -> TactileSample | None:
        """Block until a frame newer than ``after_seq`` exists; None on timeout."""
        self.require_connected()
        with self._cond:
            self._waiting_after = after_seq
            self._cond.wait_for(
                lambda: self._latest is not None and self._latest.seq > after_seq, timeout_s
            )
            self._waiting_after = -1
            sample = self._newest()
        if sample is None or sample.seq <= after_seq:
            return None
        return sample

    @abc.abstractmethod
    def stats(self) -> dict[str, int]:
        """Counters: frames received, dropped, resynchronisations, ..."""


def _close_fds(*fds: int) -> None:
    for fd in fds:
        with contextlib.suppress(OSError):
            os.close(fd)
