"""Who answers: a participant on the web page, at the keyboard, or a simulated one.

The runner only asks; a responder shows the question its own way and says
what was answered and when (monotonic ns, taken as the answer arrives, so a
slow runner never adds to a response time). The truth is never passed to a
responder: a page or a terminal cannot give it away.
"""

from __future__ import annotations

import abc
import itertools
import json
import logging
import queue
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TextIO

import numpy as np
from websockets.asyncio.server import ServerConnection
from websockets.exceptions import ConnectionClosed

from common.clocks.clock import now_ns
from common.tactile.contract import (
    MASKS,
    N_ANGLES,
    N_PATTERNS,
    N_POSITIONS,
    pattern_name,
    pattern_of,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Prompt:
    phase: str  # "practice" or "test"
    index: int  # 0-based within the phase
    total: int
    onset_ns: int  # when the stimulus started (monotonic)


@dataclass(frozen=True)
class Answer:
    pattern: int
    t_ns: int  # when the participant answered (monotonic)


class Responder(abc.ABC):
    """The participant's side of the study; ``train`` and ``ask`` are required."""

    ui: str = "?"

    def open(self) -> None:
        """Get ready (start a server, print a legend)."""
        return None  # optional hook

    def close(self) -> None:
        """Release what ``open`` took."""
        return None  # optional hook

    @abc.abstractmethod
    def train(self, pattern: int, index: int, total: int) -> None:
        """Show ``pattern``'s picture while the palm feels it; return when they go on."""

    @abc.abstractmethod
    def ask(self, prompt: Prompt) -> Answer:
        """Wait for the participant's answer to the stimulus on the palm."""

    def feedback(self, prompt: Prompt, answer: Answer, truth: int) -> None:
        """Practice only: say whether the answer was right (after it was given)."""
        return None  # optional hook

    def message(self, text: str) -> None:
        """A line for the participant (a break, the end)."""
        return None  # optional hook


# ---------------------------------------------------------------- keyboard
def ascii_picture(pattern: int) -> list[str]:
    return [" ".join("O" if MASKS[pattern][r, c] else "." for c in range(3)) for r in range(3)]


def legend() -> str:
    """The 12 patterns as numbered pictures, four rows of three (angle by position)."""
    lines = []
    for angle in range(N_ANGLES):
        trio = [pattern_of(angle, k) for k in range(N_POSITIONS)]
        lines.append("   ".join(f"{p:>2}: {pattern_name(p):<16}" for p in trio))
        pics = [ascii_picture(p) for p in trio]
        for r in range(3):
            lines.append("   ".join(f"    {pics[k][r]:<16}" for k in range(3)))
        lines.append("")
    return "\n".join(lines)


class KeyboardResponder(Responder):
    """Answers typed in a terminal: the pattern's number, then Enter."""

    ui = "keyboard"

    def __init__(self, stdin: TextIO | None = None, stdout: TextIO | None = None) -> None:
        self.stdin = stdin or sys.stdin
        self.stdout = stdout or sys.stdout

    def _print(self, text: str = "") -> None:
        self.stdout.write(text + "\n")
        self.stdout.flush()

    def _readline(self) -> str:
        line = self.stdin.readline()
        if line == "":
            raise EOFError("the keyboard input ended before the study did")
        return line.strip()

    def open(self) -> None:
        self._print("Patterns (top row of each picture: nearest the fingers):\n")
        self._print(legend())

    def train(self, pattern: int, index: int, total: int) -> None:
        self._print(f"[training {index + 1}/{total}] pattern {pattern}: {pattern_name(pattern)}")
        for line in ascii_picture(pattern):
            self._print("    " + line)
        self.stdout.write("Enter for the next one ")
        self.stdout.flush()
        self._readline()

    def ask(self, prompt: Prompt) -> Answer:
        label = "practice" if prompt.phase == "practice" else "trial"
        while True:
            self.stdout.write(f"[{label} {prompt.index + 1}/{prompt.total}] which pattern (0-11)? ")
            self.stdout.flush()
            text = self._readline()
            t = now_ns()
            if text.isdigit() and 0 <= int(text) < N_PATTERNS:
                return Answer(int(text), t)
            if text == "?":
                self._print(legend())
            else:
                self._print("  a number from 0 to 11, please ('?' shows the patterns)")

    def feedback(self, prompt: Prompt, answer: Answer, truth: int) -> None:
        if answer.pattern == truth:
            self._print("  right")
        else:
            self._print(f"  it was {truth}: {pattern_name(truth)}")

    def message(self, text: str) -> None:
        self._print(text)


# --------------------------------------------------------------- simulated
class SimulatedParticipant(Responder):
    """A model participant who feels the palm: for demos of the analysis, and tests.

    A contact point is felt when its force reaches ``felt_n`` (at the
    sensor's 1 N floor the renderer only touches the palm). The answer is
    the pattern whose cells best match what is felt (ties at random); with
    probability ``lapse`` the participant guesses instead. Response times
    are log-normal around ``rt_s``, longer when the feel is ambiguous.
    With ``realtime`` false, the study runs as fast as the display allows
    and the simulated time is what gets recorded.
    """

    ui = "simulated"

    def __init__(
        self,
        feel: Callable[[], np.ndarray | None],
        *,
        seed: int = 0,
        felt_n: float = 1.5,
        lapse: float = 0.05,
        rt_s: float = 2.5,
        realtime: bool = False,
        dwell_s: float = 0.05,
    ) -> None:
        self.feel = feel  # the stimulus on the palm now (3 x 3), or None
        self.rng = np.random.default_rng(seed)
        self.felt_n, self.lapse, self.rt_s = felt_n, lapse, rt_s
        self.realtime, self.dwell_s = realtime, dwell_s

    def train(self, pattern: int, index: int, total: int) -> None:
        time.sleep(self.dwell_s)

    def ask(self, prompt: Prompt) -> Answer:
        time.sleep(self.dwell_s)  # let the servos get there
        stim = self.feel()
        felt = np.zeros((3, 3), bool) if stim is None else np.asarray(stim) >= self.felt_n
        distance = (felt[None] != MASKS).sum(axis=(1, 2))
        candidates = np.flatnonzero(distance == distance.min())
        if self.rng.random() < self.lapse:
            pattern = int(self.rng.integers(N_PATTERNS))
        else:
            pattern = int(self.rng.choice(candidates))
        rt = float(self.rng.lognormal(np.log(self.rt_s + 0.8 * (len(candidates) - 1)), 0.3))
        if self.realtime:
            time.sleep(max(0.0, rt - self.dwell_s))
            return Answer(pattern, now_ns())
        return Answer(pattern, prompt.onset_ns + round(rt * 1e9))


# --------------------------------------------------------------------- web
STUDY_FILES = ("index.html", "study.js", "study.css")


class WebResponder(Responder):
    """The participant answers on a page: the 12 pattern pictures, one click.

    The page may be opened, closed or reloaded at any time: it is sent the
    current screen when it connects, and an answer counts only if it
    answers the question on screen (each question has its own id).
    """

    ui = "web"

    def __init__(
        self, host: str = "127.0.0.1", port: int = 8766, *, wait_log_s: float = 10.0
    ) -> None:
        from operator_side.dashboard.web import WebServer, package_files

        files = package_files("operator_side.study", STUDY_FILES)
        files.update(package_files("operator_side.dashboard", ("patterns.js",)))
        self.server = WebServer(host, port, files, self._client, name="study")
        self.answers: queue.Queue[tuple[dict[str, Any], int]] = queue.Queue()
        self.screen: dict[str, Any] = {"type": "message", "text": "Please wait…"}
        self._ids = itertools.count(1)
        self.wait_log_s = wait_log_s
        self.hello = json.dumps(
            {
                "type": "hello",
                "patterns": [
                    {
                        "id": p,
                        "name": pattern_name(p),
                        "cells": [[int(r), int(c)] for r, c in np.argwhere(MASKS[p])],
                    }
                    for p in range(N_PATTERNS)
                ],
            }
        )

    @property
    def url(self) -> str:
        return self.server.url

    def open(self) -> None:
        self.server.start()

    def close(self) -> None:
        self.server.stop()

    def _show(self, screen: dict[str, Any]) -> None:
        self.screen = screen
        text = json.dumps(screen)
        self.server.call(self._broadcast, text)

    def _broadcast(self, text: str) -> None:
        for conn in list(self.server.connections):
            self.server.send(conn, text)

    async def _client(self, conn: ServerConnection) -> None:
        log.info("study page connected from %s", conn.remote_address)
        await conn.send(self.hello)
        await conn.send(json.dumps(self.screen))
        try:
            async for raw in conn:
                t = now_ns()
                try:
                    msg = json.loads(raw)
                except ValueError:
                    continue
                if isinstance(msg, dict):
                    self.answers.put((msg, t))
        except ConnectionClosed:
            pass

    def _wait(self, kind: str, ident: int) -> tuple[dict[str, Any], int]:
        """The reply of ``kind`` to screen ``ident``; stale or malformed replies are dropped."""
        waited = 0.0
        while True:
            try:
                msg, t = self.answers.get(timeout=0.2)
            except queue.Empty:
                waited += 0.2
                if waited >= self.wait_log_s and not self.server.connections:
                    log.warning("no study page is open: open %s", self.url)
                    waited = 0.0
                continue
            if msg.get("type") == kind and msg.get("id") == ident:
                return msg, t

    def train(self, pattern: int, index: int, total: int) -> None:
        ident = next(self._ids)
        self._show(
            {"type": "train", "id": ident, "pattern": pattern, "index": index, "total": total}
        )
        self._wait("next", ident)

    def ask(self, prompt: Prompt) -> Answer:
        ident = next(self._ids)
        self._show(
            {
                "type": "ask",
                "id": ident,
                "phase": prompt.phase,
                "index": prompt.index,
                "total": prompt.total,
            }
        )
        while True:
            msg, t = self._wait("answer", ident)
            p = msg.get("pattern")
            if isinstance(p, int) and not isinstance(p, bool) and 0 <= p < N_PATTERNS:
                self._show({"type": "message", "text": "Thank you"})
                return Answer(p, t)

    def feedback(self, prompt: Prompt, answer: Answer, truth: int) -> None:
        self._show(
            {
                "type": "feedback",
                "answer": answer.pattern,
                "truth": truth,
                "correct": answer.pattern == truth,
            }
        )

    def message(self, text: str) -> None:
        self._show({"type": "message", "text": text})
