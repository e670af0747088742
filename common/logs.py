"""Logging helpers for hot loops: say a problem once, then how often it recurred."""

from __future__ import annotations

import logging
import os
import sys
import time


class BurstLog:
    """Logs the first occurrence of a problem, then at most one summary per interval.

    A flood of malformed messages must neither fill the journal nor hide the
    first example, which is the useful one.
    """

    def __init__(
        self,
        logger: logging.Logger,
        what: str,
        interval_s: float = 5.0,
        level: int = logging.WARNING,
    ) -> None:
        self.logger = logger
        self.what = what
        self.interval_s = interval_s
        self.level = level
        self.total = 0
        self._suppressed = 0
        self._last_s = -float("inf")

    def __call__(self, detail: str) -> None:
        self.total += 1
        now = time.monotonic()
        if now - self._last_s >= self.interval_s:
            if self._suppressed:
                self.logger.log(
                    self.level,
                    "%s: %d more in the last %.0f s; latest: %s",
                    self.what,
                    self._suppressed,
                    now - self._last_s,
                    detail,
                )
            else:
                self.logger.log(self.level, "%s: %s", self.what, detail)
            self._suppressed = 0
            self._last_s = now
        else:
            self._suppressed += 1


#: syslog priorities (sd-daemon(3)): what the journal files a line under
_PRIORITY = {
    logging.CRITICAL: 2,
    logging.ERROR: 3,
    logging.WARNING: 4,
    logging.INFO: 6,
    logging.DEBUG: 7,
}


def syslog_priority(levelno: int) -> int:
    """The syslog priority of a logging level (a level between two takes the lower one's)."""
    for level in sorted(_PRIORITY, reverse=True):
        if levelno >= level:
            return _PRIORITY[level]
    return 7


class JournalFormatter(logging.Formatter):
    """``<N>name: message`` on every line: the journal files each line under its severity.

    systemd reads a ``<N>`` prefix as the line's syslog priority
    (``SyslogLevelPrefix=``, on by default) and stamps the time itself, so the
    line carries neither a second time stamp nor the level's name. Every line
    of a multi-line message (a traceback) gets the prefix, or the journal would
    file the continuation lines as info.
    """

    def __init__(self, fmt: str = "%(name)s: %(message)s") -> None:
        super().__init__(fmt)

    def format(self, record: logging.LogRecord) -> str:
        prefix = f"<{syslog_priority(record.levelno)}>"
        return "\n".join(prefix + line for line in super().format(record).splitlines() or [""])


def stderr_is_journal(environ: dict[str, str] | None = None) -> bool:
    """Whether stderr is connected to the journal (``JOURNAL_STREAM``, systemd.exec(5)).

    systemd sets ``JOURNAL_STREAM=device:inode`` for a unit whose output goes
    to the journal; a child that redirected stderr elsewhere inherits the
    variable, so the device and inode of stderr must match it too.
    """
    value = (os.environ if environ is None else environ).get("JOURNAL_STREAM", "")
    try:
        device, inode = (int(part) for part in value.split(":"))
        st = os.fstat(sys.stderr.fileno())
    except (ValueError, OSError, AttributeError):  # unset, malformed, or stderr is no file
        return False
    return (st.st_dev, st.st_ino) == (device, inode)


def configure(level: int, fmt: str = "%(asctime)s %(levelname)s %(name)s: %(message)s") -> None:
    """The process's log lines on stderr: ``fmt`` on a terminal or a file, the journal's
    ``<N>`` priority prefix (and no time stamp of ours) when stderr is the journal."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JournalFormatter() if stderr_is_journal() else logging.Formatter(fmt))
    logging.basicConfig(level=level, handlers=[handler])
