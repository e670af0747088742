"""The progress bar: redrawn in place on a terminal, plain lines with no control characters."""

from __future__ import annotations

import io
import logging
import re

import pytest
from tests_support import ManualClock

from common.progress import PLAIN_STEP, Progress, clock, is_terminal


class FakeTerminal(io.StringIO):
    def isatty(self) -> bool:
        return True


@pytest.fixture
def clean_env(monkeypatch):
    monkeypatch.delenv("CI", raising=False)
    monkeypatch.setenv("TERM", "xterm")


def test_a_terminal_gets_the_bar_and_ci_a_dumb_terminal_or_a_pipe_do_not(clean_env, monkeypatch):
    assert is_terminal(FakeTerminal())
    assert not is_terminal(io.StringIO())
    monkeypatch.setenv("CI", "true")
    assert not is_terminal(FakeTerminal())
    monkeypatch.setenv("CI", "false")
    assert is_terminal(FakeTerminal())
    monkeypatch.setenv("TERM", "dumb")
    assert not is_terminal(FakeTerminal())


def test_the_bar_redraws_in_place_with_the_eta_of_its_rate(clean_env):
    out, now = FakeTerminal(), ManualClock()
    bar = Progress("collect", 10, unit="levels", stream=out, clock_fn=now)
    for done in range(1, 5):
        now.t += 3.0
        bar.update(done)
    text = out.getvalue()
    assert text.startswith("\r") and "\n" not in text
    last = text.rsplit("\r", 1)[1]
    # 4 of 10 in 12 s: 18 s to go
    assert re.match(r"collect \[=+>\s*\]\s+40% 4/10 levels 0:12 ETA 0:18", last), last
    bar.close("done")
    assert out.getvalue().endswith("\r" + " " * len(last) + "\rdone\n")


def test_a_pipe_gets_a_plain_line_per_tenth_and_no_control_characters(clean_env):
    out, now = io.StringIO(), ManualClock()
    with Progress("export", 1000, unit="s recorded", stream=out, clock_fn=now) as bar:
        for _ in range(1000):
            now.t += 0.01
            bar.advance(1)
        bar.note("a line of its own")
    lines = out.getvalue().splitlines()
    assert len(lines) <= round(1 / PLAIN_STEP) + 1
    assert not re.search(r"[\r\x1b\x00-\x08\x0b-\x1f]", out.getvalue())
    assert lines[0] == "export: 10 % (100/1000 s recorded), 0:01 so far, ETA 0:09"
    assert lines[-1] == "a line of its own"


def test_ci_on_a_terminal_is_a_log(clean_env, monkeypatch):
    monkeypatch.setenv("CI", "1")
    out = FakeTerminal()
    with Progress("bench", 4, stream=out) as bar:
        for i in range(4):
            bar.update(i + 1)
    assert "\r" not in out.getvalue() and "\x1b" not in out.getvalue()


def test_a_log_line_takes_the_bar_off_its_line_first(clean_env):
    out, now = FakeTerminal(), ManualClock()
    handler = logging.StreamHandler(out)
    root = logging.getLogger()
    root.addHandler(handler)
    try:
        bar = Progress("collect", 10, stream=out, clock_fn=now)
        bar.update(3, force=True)
        shown = len(bar.line(80))
        logging.getLogger("deepxpalm.test").warning("the world shows 4")
        bar.close()
        logging.getLogger("deepxpalm.test").warning("after the bar")
    finally:
        root.removeHandler(handler)
    text = out.getvalue()
    assert "\r" + " " * shown + "\rthe world shows 4\n" in text
    assert text.endswith("after the bar\n") and "\rafter" not in text


def test_durations_read_as_a_clock():
    assert clock(5) == "0:05"
    assert clock(754.4) == "12:34"
    assert clock(6197) == "1:43:17"
    assert clock(None) == "?"
