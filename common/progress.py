"""Progress of long work: a bar redrawn in place on a terminal, a few plain lines anywhere else.

On a terminal (the stream is a TTY, ``CI`` is unset and ``TERM`` is not
``dumb``) one line is redrawn with a carriage return, at most ten times a
second: the label, a bar, the share done, what is being done, the time so far
and an ETA. Anywhere else (a log, a pipe, a CI job) it writes no control
characters at all: a plain line each time the work passes another tenth, and
the lines the caller adds (``note``), so a log still says how far it got.

The bench, ``deepxpalm collect``, ``export``, ``train`` and ``soak`` all use it; it
needs nothing beyond the standard library, so the operator's install and the
bench have it too.
"""

from __future__ import annotations

import logging
import os
import sys
import threading
import time
from collections.abc import Callable
from typing import Any, TextIO

#: the bar's width in characters between its brackets
BAR_WIDTH = 24
#: the shortest time between two redraws of the bar
REDRAW_S = 0.1
#: a plain line each time the work passes another this much of the whole
PLAIN_STEP = 0.1


def is_terminal(stream: Any) -> bool:
    """Whether a bar redrawn in place belongs on ``stream``: a TTY, not CI, not a dumb terminal."""
    if os.environ.get("CI", "").lower() not in ("", "0", "false", "no"):
        return False
    if os.environ.get("TERM") == "dumb":
        return False
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):
        return False


def clock(seconds: float | None) -> str:
    """``1:02:03``, ``2:03`` or ``?``: how a duration reads on the line."""
    if seconds is None or seconds != seconds or seconds < 0:
        return "?"
    s = round(seconds)
    h, rest = divmod(s, 3600)
    m, s = divmod(rest, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


class Progress:
    """One piece of long work, reported on ``stream`` (stderr unless given).

    ``update`` says how far it is: ``done`` of ``total`` (the ETA then follows
    from the rate so far), or a ``fraction`` and an ``eta_s`` the caller
    worked out itself (the bench, from its last run). ``eta_open`` marks an ETA
    that is a lower bound (some of the work left has no estimate). Use it as a
    context manager, or call ``close``.
    """

    def __init__(
        self,
        label: str,
        total: float | None = None,
        *,
        unit: str = "",
        stream: TextIO | None = None,
        terminal: bool | None = None,
        clock_fn: Callable[[], float] = time.monotonic,
    ) -> None:
        self.label = label
        self.total = total
        self.unit = unit
        self.stream = stream if stream is not None else sys.stderr
        self.terminal = is_terminal(self.stream) if terminal is None else terminal
        self._now = clock_fn
        self.t0 = clock_fn()
        self.done: float = 0.0
        self.fraction: float | None = None
        self.detail = ""
        self.eta_s: float | None = None
        self.eta_open = False
        self._shown = 0  # characters of the bar on the screen now
        self._drawn_at = -1e9
        self._plain_next = PLAIN_STEP
        self._lock = threading.RLock()
        self._log_filter: _ClearBar | None = None
        self._closed = False
        if self.terminal:
            self._log_filter = _ClearBar(self)
            for handler in _stream_handlers(self.stream):
                handler.addFilter(self._log_filter)

    # ---------------------------------------------------------------- reporting
    def update(
        self,
        done: float | None = None,
        total: float | None = None,
        *,
        fraction: float | None = None,
        detail: str | None = None,
        eta_s: float | None = None,
        eta_open: bool = False,
        force: bool = False,
        draw: bool = True,
    ) -> None:
        """How far the work is; redrawn (terminal) or a plain line at each tenth (elsewhere).

        ``force`` redraws even within a tenth of a second of the last; ``draw=False`` only
        keeps the state (a ``note`` about to follow draws it).
        """
        with self._lock:
            if done is not None:
                self.done = done
            if total is not None:
                self.total = total
            if detail is not None:
                self.detail = detail
            self.fraction = fraction
            self.eta_s = eta_s
            self.eta_open = eta_open
            if draw:
                self._report(force)

    def advance(self, n: float = 1, detail: str | None = None) -> None:
        """``n`` more units done."""
        with self._lock:
            self.update(self.done + n, detail=detail)

    def note(self, line: str, stream: TextIO | None = None) -> None:
        """A line of its own (a section's result, a warning), above the bar on a terminal."""
        with self._lock:
            out = stream if stream is not None else self.stream
            self.clear()
            out.write(line + "\n")
            out.flush()
            if self.terminal and not self._closed:
                self._draw()

    def clear(self) -> None:
        """Take the bar off the screen (before a prompt or another program's output)."""
        with self._lock:
            if self._shown:
                self.stream.write("\r" + " " * self._shown + "\r")
                self.stream.flush()
                self._shown = 0

    def close(self, summary: str | None = None) -> None:
        """The end: the bar is taken off (a terminal) and ``summary``, if any, written."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            if self._log_filter is not None:
                for handler in _stream_handlers(self.stream):
                    handler.removeFilter(self._log_filter)
            self.clear()
            if summary:
                self.stream.write(summary + "\n")
                self.stream.flush()

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---------------------------------------------------------------- what is shown
    def share(self) -> float | None:
        """The share of the work done, 0..1, or None when nothing says."""
        if self.fraction is not None:
            return min(max(self.fraction, 0.0), 1.0)
        if self.total:
            return min(max(self.done / self.total, 0.0), 1.0)
        return None

    def elapsed(self) -> float:
        return self._now() - self.t0

    def eta(self) -> float | None:
        """The caller's ETA, or the rate so far applied to what is left."""
        if self.eta_s is not None or self.fraction is not None:
            return self.eta_s
        if not self.total or self.done <= 0:
            return None
        return self.elapsed() / self.done * max(self.total - self.done, 0)

    def _eta_text(self) -> str:
        eta = self.eta()
        return "ETA " + (">" if self.eta_open and eta is not None else "") + clock(eta)

    def _count(self) -> str:
        if self.total is None:
            return f"{_num(self.done)}{' ' + self.unit if self.unit else ''}"
        return f"{_num(self.done)}/{_num(self.total)}{' ' + self.unit if self.unit else ''}"

    def line(self, width: int | None = None) -> str:
        """The bar's line as drawn on a terminal (no control characters), cut to ``width``."""
        share = self.share()
        parts = [self.label]
        if share is not None:
            filled = int(share * BAR_WIDTH)
            head = ">" if filled < BAR_WIDTH else ""
            parts.append("[" + ("=" * filled + head).ljust(BAR_WIDTH) + "]")
            parts.append(f"{share * 100:3.0f}%")
        if self.fraction is None:
            parts.append(self._count())
        if self.detail:
            parts.append(self.detail)
        parts.append(f"{clock(self.elapsed())} {self._eta_text()}")
        text = " ".join(parts)
        return text if width is None else text[: max(width - 1, 10)]

    def plain_line(self) -> str:
        """A line for a log: how far, how long, ETA."""
        share = self.share()
        head = f"{self.label}: " + (f"{share * 100:.0f} %" if share is not None else "")
        what = [] if self.fraction is not None else [self._count()]
        if self.detail:
            what.append(self.detail)
        tail = f"{clock(self.elapsed())} so far, {self._eta_text()}"
        return head + (f" ({', '.join(what)})" if what else "") + f", {tail}"

    # ---------------------------------------------------------------- drawing
    def _report(self, force: bool) -> None:
        if self._closed:
            return
        if self.terminal:
            if force or self._now() - self._drawn_at >= REDRAW_S:
                self._draw()
            return
        share = self.share()
        if share is None or share < self._plain_next or share >= 1.0:
            return
        while self._plain_next <= share:
            self._plain_next += PLAIN_STEP
        self.stream.write(self.plain_line() + "\n")
        self.stream.flush()

    def _draw(self) -> None:
        text = self.line(_width(self.stream))
        pad = max(self._shown - len(text), 0)
        self.stream.write("\r" + text + " " * pad)
        self.stream.flush()
        self._shown = len(text)
        self._drawn_at = self._now()


def _num(x: float) -> str:
    return f"{x:.0f}" if float(x).is_integer() else f"{x:.1f}"


def _width(stream: Any) -> int:
    try:
        columns = os.get_terminal_size(stream.fileno()).columns
    except (AttributeError, ValueError, OSError):
        columns = 0
    return columns if columns > 0 else 80  # a new pseudo-terminal says 0 until it is sized


def _stream_handlers(stream: Any) -> list[logging.Handler]:
    """The root logger's handlers that write to ``stream``, where a log line meets the bar."""
    return [
        h
        for h in logging.getLogger().handlers
        if isinstance(h, logging.StreamHandler) and getattr(h, "stream", None) is stream
    ]


class _ClearBar(logging.Filter):
    """Takes the bar off the line before a log record is written there; the next update redraws."""

    def __init__(self, progress: Progress) -> None:
        super().__init__()
        self.progress = progress

    def filter(self, record: logging.LogRecord) -> bool:
        self.progress.clear()
        return True
