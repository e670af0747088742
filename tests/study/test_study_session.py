"""Whole study sessions on the in-memory servo bus, answered by scripted participants.

The scripted participant of the main test answers through the answer page's
own WebSocket, and decides what it felt from the servos alone: it reads the
bus's present positions, runs them through forward kinematics, and names the
pattern whose cells the contact points press. So a pass means the right
pattern reached the palm, not just the right number the file.
"""

from __future__ import annotations

import io
import json
import threading
import time

import numpy as np
import pytest
from websockets.sync.client import connect

from common.tactile.contract import MASKS, N_PATTERNS
from deploy.cli import main
from operator_side.palm.linkglide import forward_kinematics
from operator_side.servos.in_memory import InMemoryServoBus
from operator_side.study.analysis import analyse_trials, load_test_trials
from operator_side.study.display import PalmDisplay
from operator_side.study.protocol import (
    ResultsFile,
    StudyConfig,
    read_records,
    results_path,
    trial_order,
)
from operator_side.study.report import write_report
from operator_side.study.responders import (
    Answer,
    KeyboardResponder,
    Prompt,
    Responder,
    WebResponder,
)
from operator_side.study.runner import Session

pytestmark = [pytest.mark.slow, pytest.mark.timeout(120)]

FAST = {"pause_s": 0.0, "feedback_s": 0.0}


def contact_points(bus: InMemoryServoBus, display: PalmDisplay) -> np.ndarray:
    counts = np.array([bus.read_positions()[i] for i in range(1, 7)])
    angles = display.calibration.counts_to_angles(counts)
    return forward_kinematics(angles, display.renderer_config.geometry)


def goal_points(display: PalmDisplay) -> np.ndarray:
    """The contact points the display is heading for: its renderer's goal for its stimulus."""
    goal = display.renderer.target_counts(display.current_stimulus)
    angles = display.calibration.counts_to_angles(goal)
    return forward_kinematics(angles, display.renderer_config.geometry)


def felt_pattern(points: np.ndarray, display: PalmDisplay) -> int | None:
    """The pattern three resting contact points press, or None if they press none."""
    contact = display.renderer_config.contact
    cols = np.array(contact.column_x_mm)
    pressed = np.zeros((3, 3), bool)
    for row, (x, y) in enumerate(points):
        if np.hypot(x - contact.retract_point_mm[0], y - contact.retract_point_mm[1]) < 0.5:
            continue  # lifted
        col = int(np.argmin(abs(cols - x)))
        if abs(cols[col] - x) > 0.5 or y < contact.palm_y_mm - 0.05:
            return None  # on its way
        pressed[row, col] = True
    matches = [p for p in range(N_PATTERNS) if np.array_equal(MASKS[p], pressed)]
    return matches[0] if matches else None


class ScriptedPage(threading.Thread):
    """Answers on the study page's WebSocket: what the servos press, except 4 is taken for 5."""

    def __init__(self, url: str, bus: InMemoryServoBus, display: PalmDisplay) -> None:
        super().__init__(daemon=True)
        self.url, self.bus, self.display = url, bus, display
        self.screens: list[dict] = []
        self.trained: list[int] = []
        self.felt: list[int] = []
        self.error: BaseException | None = None
        self.done = threading.Event()

    def feel(self, timeout_s: float = 10.0) -> int:
        """What the palm presses once the linkages have come to rest where the display aims.

        On their way from the retract point the contact points can cross the
        palm's columns, so a pattern counts only when two readings 50 ms
        apart agree, no point moved across the palm in between (noise in the
        force moves them only in depth), and the points press what the
        display's goal for its current stimulus presses: a display thread
        starved mid-way holds the linkages still on a pattern they were only
        crossing (a loaded run read 1 on the way to 0).
        """
        deadline = time.monotonic() + timeout_s
        before = contact_points(self.bus, self.display)
        while time.monotonic() < deadline:
            time.sleep(0.05)
            now = contact_points(self.bus, self.display)
            p = felt_pattern(now, self.display)
            still = np.abs(now[:, 0] - before[:, 0]).max() < 0.05
            arrived = p == felt_pattern(goal_points(self.display), self.display)
            if p is not None and still and arrived and felt_pattern(before, self.display) == p:
                return p
            before = now
        raise AssertionError("the palm never showed a whole pattern")

    def run(self) -> None:
        try:
            with connect(self.url) as ws:
                while not self.done.is_set():
                    msg = json.loads(ws.recv(timeout=20))
                    self.screens.append(msg)
                    if msg["type"] == "train":
                        self.trained.append(msg["pattern"])
                        assert self.feel() == msg["pattern"]
                        ws.send(json.dumps({"type": "next", "id": msg["id"]}))
                    elif msg["type"] == "ask":
                        p = self.feel()
                        self.felt.append(p)
                        answer = 5 if p == 4 else p
                        ws.send(json.dumps({"type": "answer", "id": msg["id"], "pattern": answer}))
                    elif msg["type"] == "message" and msg["text"].startswith("Done"):
                        self.done.set()
        except BaseException as e:
            self.error = e
            self.done.set()


def test_a_whole_masked_session_on_the_page_then_its_analysis(tmp_path):
    config = StudyConfig(mode="masked", seed=11, **FAST)
    config.renderer.max_step_deg_per_cycle = 30.0  # quick moves: the rate limit is not on trial
    bus = InMemoryServoBus()
    display = PalmDisplay(bus, config.renderer, frame_rate_hz=config.frame_rate_hz)
    responder = WebResponder(port=0)
    path = results_path(tmp_path, "S01", "masked")
    results = ResultsFile(path, "S01", "masked", 11)
    display.connect()
    responder.open()
    page = ScriptedPage(responder.server.ws_url, bus, display)
    page.start()
    # The session waits for a page as long as none is open, as it should for a participant:
    # a scripted page that failed is reported at once, not after the test's timeout.
    outcome: dict = {}

    def run_session() -> None:
        try:
            outcome["summary"] = Session(config, "S01", 11, display, responder, results).run()
        except BaseException as e:
            outcome["error"] = e

    session = threading.Thread(target=run_session, daemon=True)
    try:
        session.start()
        while session.is_alive() and page.error is None:
            session.join(timeout=0.2)
    finally:
        display.close()
        responder.close()
        results.close()
        page.done.set()
        page.join(timeout=5)
    assert page.error is None, f"the scripted page failed: {page.error!r}"
    assert "error" not in outcome, f"the session failed: {outcome['error']!r}"
    summary = outcome["summary"]

    # Training showed every pattern in order, and the palm felt each one.
    assert page.trained == list(range(12))
    # The test: 60 trials, each pattern 5 times, in the seeded order, and what
    # the palm pressed was the rendered pattern every time.
    records = read_records(path)
    test = [r for r in records if r.get("kind") == "trial" and r["phase"] == "test"]
    practice = [r for r in records if r.get("kind") == "trial" and r["phase"] == "practice"]
    assert len(test) == 60 and len(practice) == 12
    assert [r["pattern"] for r in test] == trial_order(11, 5)
    assert np.bincount([r["pattern"] for r in test]).tolist() == [5] * 12
    assert page.felt == [r["pattern"] for r in practice + test]
    for r in test:
        assert np.array_equal(np.array(r["stimulus"]) > 0, MASKS[r["pattern"]])
        assert 0 < r["response_time_s"] < 5 and r["ui"] == "web"
    assert summary.test_trials == 60 and summary.correct == 55
    assert bus.status()["refused"] == 0 and not bus.torque_enabled

    # The analysis, end to end: 4 was always taken for 5.
    a = analyse_trials(load_test_trials([tmp_path]), "masked")
    assert a.counts[4, 5] == 5 and a.per_pattern[4] == 0.0
    assert a.overall == pytest.approx(55 / 60)
    assert a.angle_only == pytest.approx(1.0)
    paths = write_report([a], tmp_path / "report")
    assert "91.67% (55 of 60)" in paths["markdown"].read_text()


class Typist(KeyboardResponder):
    """Keyboard input from a script; counts the prompts it saw."""

    def __init__(self, lines: list[str]) -> None:
        self.out = io.StringIO()
        super().__init__(io.StringIO("".join(line + "\n" for line in lines)), self.out)


def test_keyboard_answers_are_checked_and_timed(tmp_path):
    config = StudyConfig(mode="ideal", repetitions=1, practice_rounds=0, seed=3, **FAST)
    order = trial_order(3, 1)
    # Training (12 x Enter), then: a typo, an out-of-range number, '?', then the answers.
    lines = [""] * 12 + ["x", "12", "?"] + [str(p) for p in order]
    typist = Typist(lines)
    bus = InMemoryServoBus()
    path = results_path(tmp_path, "K1", "ideal")
    with PalmDisplay(bus, config.renderer) as display:
        results = ResultsFile(path, "K1", "ideal", 3)
        typist.open()
        summary = Session(config, "K1", 3, display, typist, results).run()
        results.close()
    assert summary.correct == summary.test_trials == 12
    shown = typist.out.getvalue()
    assert "a number from 0 to 11" in shown and shown.count("45 deg left") >= 3
    test = [r for r in read_records(path) if r.get("kind") == "trial"]
    assert [r["pattern"] for r in test] == order
    assert all(r["ui"] == "keyboard" and r["response_time_s"] >= 0 for r in test)


class CrashAfter(Responder):
    """Answers right, then fails mid-session as a power cut would."""

    ui = "scripted"

    def __init__(self, display: PalmDisplay, answers_before_crash: int | None) -> None:
        self.display = display
        self.left = answers_before_crash

    def train(self, pattern: int, index: int, total: int) -> None:
        pass

    def ask(self, prompt: Prompt) -> Answer:
        if self.left is not None:
            if self.left == 0:
                raise RuntimeError("power cut")
            self.left -= 1
        stim = self.display.first_stimulus
        pattern = next(p for p in range(12) if np.array_equal(MASKS[p], stim > 0))
        return Answer(pattern, prompt.onset_ns + 1_000_000_000)


def test_a_crashed_session_keeps_its_answers_and_resumes_where_it_stopped(tmp_path):
    config = StudyConfig(mode="ideal", repetitions=2, practice_rounds=0, seed=5, **FAST)
    path = results_path(tmp_path, "R1", "ideal")

    def session(answers_before_crash: int | None) -> None:
        with PalmDisplay(InMemoryServoBus(), config.renderer) as display:
            results = ResultsFile(path, "R1", "ideal", 5)
            try:
                Session(config, "R1", 5, display, CrashAfter(display, answers_before_crash),
                        results).run()  # fmt: skip
            finally:
                results.close()

    with pytest.raises(RuntimeError, match="power cut"):
        session(7)
    assert len([r for r in read_records(path) if r.get("kind") == "trial"]) == 7
    with path.open("a") as f:
        f.write('{"kind":"trial","phase":"te')  # a line torn by the crash
    session(None)
    trials = [r for r in read_records(path) if r.get("kind") == "trial"]
    assert [r["index"] for r in trials] == list(range(24))
    assert [r["pattern"] for r in trials] == trial_order(5, 2)
    sessions = [r for r in read_records(path) if r.get("kind") == "session"]
    assert [s["resumed"] for s in sessions] == [False, True]

    # Another seed on the same file is refused instead of mixing two orders.
    from common.errors import ConfigError

    with pytest.raises(ConfigError, match="--seed 5"):
        ResultsFile(path, "R1", "ideal", 6)


def test_the_cli_runs_a_simulated_participant_in_each_mode(tmp_path, capsys):
    for mode in ("direct", "masked"):
        code = main(
            ["study", "run", "--participant", "SIM", "--ui", "simulated", "--mode", mode,
             "--out", str(tmp_path), "--set", "repetitions=1", "--set", "practice_rounds=0",
             "--set", "pause_s=0", "--no-training"]
        )  # fmt: skip
        assert code == 0
    out = capsys.readouterr().out
    assert "SIM direct:" in out and "SIM masked:" in out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["SIM_direct.jsonl", "SIM_masked.jsonl"]
    trials = load_test_trials([tmp_path])
    assert len(trials) == 24 and {t["mode"] for t in trials} == {"direct", "masked"}
    # Masked rendering presses exactly the pattern's cells; direct does not always.
    masked = [t for t in trials if t["mode"] == "masked"]
    assert all(np.array_equal(np.array(t["stimulus"]) > 0, MASKS[t["pattern"]]) for t in masked)


def test_participant_ids_cannot_escape_the_results_directory(tmp_path):
    from common.errors import ConfigError

    for bad in ("../x", "a/b", "", "名前", "x" * 65):
        with pytest.raises(ConfigError):
            results_path(tmp_path, bad, "masked")
