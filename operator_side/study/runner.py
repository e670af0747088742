"""One session of the perception study: training, practice, then the recorded test.

The session owns the order of things and the results file; the display owns
the servos and the responder owns the participant's side. Whatever happens
(a crash, Ctrl-C, a servo error), the palm is lifted by the display's owner
and every answered trial is already on disk.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from common.tactile.contract import N_PATTERNS, classes_of, pattern_name
from operator_side.study.display import PalmDisplay, StimulusMaker, wait_s
from operator_side.study.protocol import (
    ResultsFile,
    StudyConfig,
    now_wall,
    practice_order,
    trial_order,
    trial_rng,
)
from operator_side.study.responders import Answer, Prompt, Responder

log = logging.getLogger(__name__)


@dataclass
class SessionSummary:
    participant: str
    mode: str
    seed: int
    test_trials: int  # answered in this file, by this run and earlier ones
    correct: int
    resumed_from: int  # test trials already done when this run started

    @property
    def recognition_rate(self) -> float:
        return self.correct / self.test_trials if self.test_trials else 0.0


class Session:
    """One participant in one mode; ``run()`` runs or resumes it."""

    def __init__(
        self,
        config: StudyConfig,
        participant: str,
        seed: int,
        display: PalmDisplay,
        responder: Responder,
        results: ResultsFile,
    ) -> None:
        self.config = config
        self.participant = participant
        self.seed = seed
        self.display = display
        self.responder = responder
        self.results = results
        self.maker = StimulusMaker(config)

    def run(self, *, training: bool = True) -> SessionSummary:
        cfg, say = self.config, self.responder.message
        order = trial_order(self.seed, cfg.repetitions)
        done = self.results.completed_test_trials()
        self.results.write_header(cfg, self.responder.ui)
        if len(done) >= len(order):
            log.info("%s's %s session is already complete", self.participant, cfg.mode)
        elif done:
            log.info(
                "resuming %s: %d of %d test trials done", self.participant, len(done), len(order)
            )
            say(f"Welcome back. {len(order) - len(done)} patterns to go.")
            wait_s(cfg.pause_s)
        elif training:
            self.training()
            self.practice()
            say("Now the test. No feedback from here on.")
            wait_s(cfg.pause_s)
        for index, pattern in enumerate(order):
            if index not in done:
                self.trial("test", index, len(order), pattern)
        self.display.lift()
        say("Done. Thank you!")
        test = [
            r for r in self.results.records if r.get("kind") == "trial" and r.get("phase") == "test"
        ]
        return SessionSummary(
            participant=self.participant,
            mode=cfg.mode,
            seed=self.seed,
            test_trials=len(test),
            correct=sum(1 for r in test if r["correct"]),
            resumed_from=len(done),
        )

    def training(self) -> None:
        """Each pattern with its picture, in order, while the palm feels it."""
        for pattern in range(N_PATTERNS):
            source, _ = self.maker.source(pattern, trial_rng(self.seed, "training", pattern))
            self.display.show(source)
            self.responder.train(pattern, pattern, N_PATTERNS)
            self.display.lift()
            wait_s(self.config.pause_s / 2)

    def practice(self) -> None:
        """Blind, with feedback; recorded as phase "practice", never analysed."""
        order = practice_order(self.seed, self.config.practice_rounds)
        if order:
            self.responder.message("Practice: feel, answer, and see whether you were right.")
            wait_s(self.config.pause_s)
        for index, pattern in enumerate(order):
            prompt, answer = self.trial("practice", index, len(order), pattern)
            self.responder.feedback(prompt, answer, pattern)
            wait_s(self.config.feedback_s)

    def trial(self, phase: str, index: int, total: int, pattern: int) -> tuple[Prompt, Answer]:
        """Lift, pause, render, ask, lift, record (flushed to disk before returning)."""
        self.display.lift()
        wait_s(self.config.pause_s)
        source, grip = self.maker.source(pattern, trial_rng(self.seed, phase, index))
        onset = self.display.show(source)
        shown = self.display.first_stimulus
        prompt = Prompt(phase=phase, index=index, total=total, onset_ns=onset)
        answer = self.responder.ask(prompt)
        self.display.lift()
        rt_s = (answer.t_ns - onset) / 1e9
        self.results.append(
            {
                "kind": "trial",
                "participant": self.participant,
                "mode": self.config.mode,
                "seed": self.seed,
                "phase": phase,
                "index": index,
                "pattern": pattern,
                "answer": answer.pattern,
                "correct": answer.pattern == pattern,
                "angle_correct": classes_of(answer.pattern)[0] == classes_of(pattern)[0],
                "response_time_s": round(rt_s, 4),
                "grip_level": grip,
                "stimulus": None if shown is None else np.round(shown.astype(float), 3).tolist(),
                "ui": self.responder.ui,
                "t_wall": now_wall(),
            }
        )
        log.info(
            "%s %s %d/%d: %s -> %s (%.2f s)",
            self.participant,
            phase,
            index + 1,
            total,
            pattern_name(pattern),
            pattern_name(answer.pattern),
            rt_s,
        )
        return prompt, answer
