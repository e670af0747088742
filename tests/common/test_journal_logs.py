"""Under systemd each line carries its syslog priority, so `journalctl -p err` finds the errors."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
from pathlib import Path

from common.logs import JournalFormatter, stderr_is_journal, syslog_priority


def _journal_env(stderr_path: Path) -> dict[str, str]:
    st = os.stat(stderr_path)
    return {**os.environ, "JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"}


def test_an_error_line_of_a_node_under_the_journal_starts_with_its_priority(tmp_path: Path) -> None:
    """A real `deepxpalm` process whose stderr is the stream JOURNAL_STREAM names."""
    err = tmp_path / "stderr"
    err.touch()
    with err.open("w") as stderr:
        proc = subprocess.run(
            [sys.executable, "-m", "deploy.cli", "robot", "--config", str(tmp_path / "none.toml")],
            stderr=stderr,
            stdout=subprocess.DEVNULL,
            env=_journal_env(err),
            timeout=60,
        )
    assert proc.returncode != 0
    logged = [line for line in err.read_text().splitlines() if line.startswith("<")]
    assert logged, err.read_text()
    assert logged[0].startswith("<3>deepxpalm: "), logged
    assert "none.toml" in logged[0]


def test_without_the_journal_lines_keep_their_time_and_level(tmp_path: Path) -> None:
    err = tmp_path / "stderr"
    with err.open("w") as stderr:
        subprocess.run(
            [sys.executable, "-m", "deploy.cli", "robot", "--config", str(tmp_path / "none.toml")],
            stderr=stderr,
            stdout=subprocess.DEVNULL,
            env={k: v for k, v in os.environ.items() if k != "JOURNAL_STREAM"},
            timeout=60,
        )
    text = err.read_text()
    assert " ERROR deepxpalm: " in text and not text.startswith("<"), text


def test_a_stream_inherited_by_a_child_that_redirected_stderr_is_not_the_journal(
    tmp_path: Path,
) -> None:
    other = tmp_path / "other"
    other.touch()
    st = os.stat(other)
    assert not stderr_is_journal({"JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"})
    assert not stderr_is_journal({"JOURNAL_STREAM": "garbage"})
    assert not stderr_is_journal({})


def test_every_line_of_a_traceback_carries_the_priority() -> None:
    try:
        raise ValueError("boom")
    except ValueError:
        record = logging.LogRecord("n", logging.ERROR, __file__, 1, "failed", None, sys.exc_info())
    lines = JournalFormatter().format(record).splitlines()
    assert len(lines) > 2
    assert all(line.startswith("<3>") for line in lines), lines
    assert lines[0] == "<3>n: failed"


def test_priorities_follow_syslog() -> None:
    assert [syslog_priority(v) for v in (50, 40, 30, 20, 10, 25, 5)] == [2, 3, 4, 6, 7, 6, 7]
