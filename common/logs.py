"""Logging helpers for hot loops: say a problem once, then how often it recurred."""

from __future__ import annotations

import logging
import time


class BurstLog:
    """Logs the first occurrence of a problem, then at most one summary per interval.

    A flood of malformed messages must neither fill the journal nor hide the
    first example, which is the useful one.
    """

    def __init__(self, logger: logging.Logger, what: str, interval_s: float = 5.0) -> None:
        self.logger = logger
        self.what = what
        self.interval_s = interval_s
        self.total = 0
        self._suppressed = 0
        self._last_s = -float("inf")

    def __call__(self, detail: str) -> None:
        self.total += 1
        now = time.monotonic()
        if now - self._last_s >= self.interval_s:
            if self._suppressed:
                self.logger.warning(
                    "%s: %d more in the last %.0f s; latest: %s",
                    self.what,
                    self._suppressed,
                    now - self._last_s,
                    detail,
                )
            else:
                self.logger.warning("%s: %s", self.what, detail)
            self._suppressed = 0
            self._last_s = now
        else:
            self._suppressed += 1
