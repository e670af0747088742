"""The study's answer page in headless chromium: training, practice with feedback, test clicks.

Lives beside the dashboard's browser test to share its DevTools helper.
"""

from __future__ import annotations

import threading

import numpy as np
import pytest
from headless_chromium import Chromium, needs_chromium

from common.tactile.contract import MASKS
from operator_side.servos.in_memory import InMemoryServoBus
from operator_side.study.display import PalmDisplay
from operator_side.study.protocol import ResultsFile, StudyConfig, read_records, results_path
from operator_side.study.responders import WebResponder
from operator_side.study.runner import Session

pytestmark = [
    pytest.mark.slow,
    pytest.mark.timeout(90),
    needs_chromium,
]


def test_a_participant_clicks_through_training_practice_and_test(tmp_path):
    config = StudyConfig(
        mode="ideal", repetitions=1, practice_rounds=1, seed=2, pause_s=0.0, feedback_s=0.3
    )
    display = PalmDisplay(InMemoryServoBus(), config.renderer)
    responder = WebResponder(port=0)
    path = results_path(tmp_path, "B1", "ideal")
    results = ResultsFile(path, "B1", "ideal", 2)
    display.connect()
    responder.open()
    outcome: list = []

    def run() -> None:
        try:
            outcome.append(Session(config, "B1", 2, display, responder, results).run())
        except BaseException as e:
            outcome.append(e)

    session = threading.Thread(target=run, daemon=True)
    session.start()
    try:
        with Chromium(width=900, height=900) as browser:
            browser.navigate(responder.url)
            for k in range(12):
                browser.wait_for(
                    f"study.screen && study.screen.type === 'train' && study.screen.index === {k}"
                    " && !document.getElementById('train').hidden",
                    5,
                )
                name = browser.evaluate("document.getElementById('train-name').textContent")
                assert name.startswith(f"{k} · ")
                browser.click("#next")
            mistake_truth = None
            for answered in range(24):  # 12 practice, then 12 test
                browser.wait_for(
                    "study.screen && study.screen.type === 'ask' && !study.screen.answered"
                    " && !document.getElementById('ask').hidden",
                    5,
                )
                truth = next(
                    p for p in range(12) if np.array_equal(MASKS[p], display.first_stimulus > 0)
                )
                # Practice: one deliberate mistake, to see the feedback name the truth.
                pick = (truth + 1) % 12 if answered == 0 else truth
                browser.click(f"#choice-{pick}")
                if answered == 0:
                    mistake_truth = truth
            browser.wait_for(
                "document.getElementById('message-text').textContent.startsWith('Done')"
            )
            # Every practice answer got its feedback; the mistake was named.
            shown = browser.evaluate("study.shown")
            assert len(shown) == 12
            assert shown[0].startswith(f"It was {mistake_truth} · ") and shown[1:] == ["Right"] * 11
            assert browser.page_errors() == []
    finally:
        session.join(timeout=10)
        display.close()
        responder.close()
        results.close()
    summary = outcome[0]
    assert not isinstance(summary, BaseException), summary
    assert summary.correct == summary.test_trials == 12
    trials = [r for r in read_records(path) if r.get("kind") == "trial"]
    assert [r["phase"] for r in trials] == ["practice"] * 12 + ["test"] * 12
    assert trials[0]["correct"] is False and all(r["ui"] == "web" for r in trials)
