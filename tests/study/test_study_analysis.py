"""The analysis against the paper's own numbers and against a hand-computed ANOVA."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from common.errors import ConfigError
from deploy.cli import main
from operator_side.study.analysis import (
    analyse_confusion,
    analyse_trials,
    read_confusion_csv,
)
from operator_side.study.report import write_report

# the timeout: pingouin's first import is slow on a cold disk
pytestmark = [pytest.mark.slow, pytest.mark.untimed, pytest.mark.timeout(120)]

TABLE_I = Path(__file__).parent / "data" / "paper_table1.csv"


def test_table_i_gives_the_papers_recognition_rates():
    counts = read_confusion_csv(TABLE_I, presentations_per_row=50)
    assert counts.sum(axis=1).tolist() == [50] * 12
    a = analyse_confusion(counts, "direct")
    # The diagonal of Table I: 0.16 0.06 0.16 0.14 0 0.10 0.06 0.02 0.12 0.08 0.08 0.18,
    # 1.16 in all, over 12 patterns.
    assert a.correct == 58 and a.trials == 600
    assert a.overall == pytest.approx(0.0966667, abs=1e-6)
    assert round(100 * a.overall, 2) == 9.67
    assert a.diagonal_mean == pytest.approx(a.overall)
    # "the overall recognition increases to 28% if only the angles are considered"
    assert a.angle_only == pytest.approx(0.28, abs=1e-12)
    assert a.per_pattern[4] == 0.0 and a.per_pattern[11] == pytest.approx(0.18)
    assert a.anova_pattern is None and "no ANOVA" in a.warnings[0]


def test_the_cli_reports_table_i_with_a_figure(tmp_path, capsys):
    out = tmp_path / "report"
    code = main(
        ["study", "analyse", "--confusion", str(TABLE_I), "--presentations", "50",
         "--mode", "direct", "--out", str(out)]
    )  # fmt: skip
    assert code == 0
    printed = capsys.readouterr().out
    assert "recognised 9.67%" in printed and "angle only 28.00%" in printed
    md = (out / "report.md").read_text()
    assert "| recognition rate (pattern) | 9.67% (58 of 600) |" in md
    report = json.loads((out / "report.json").read_text())["analyses"][0]
    assert report["recognition_rate"] == pytest.approx(0.096667, abs=1e-6)
    png = (out / "confusion_direct.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000


def test_proportions_need_a_presentation_count_that_makes_whole_answers(tmp_path):
    with pytest.raises(ConfigError, match="presentations"):
        read_confusion_csv(TABLE_I)
    with pytest.raises(ConfigError, match="whole presentations"):
        read_confusion_csv(TABLE_I, presentations_per_row=30)
    bad = tmp_path / "small.csv"
    bad.write_text("1,0\n0,1\n")
    with pytest.raises(ConfigError, match="12 x 12"):
        read_confusion_csv(bad)


def _trials(rates: np.ndarray, reps: int = 5) -> list[dict]:
    """Trials whose per-participant, per-pattern recognition is exactly ``rates`` (k/reps)."""
    out = []
    for w, row in enumerate(rates):
        for p, rate in enumerate(row):
            hits = round(rate * reps)
            for k in range(reps):
                answer = p if k < hits else (p + 1) % 12
                out.append(
                    {
                        "participant": f"P{w:02d}",
                        "mode": "masked",
                        "phase": "test",
                        "pattern": p,
                        "answer": answer,
                        "response_time_s": 2.0 + 0.1 * p + 0.01 * w,
                    }
                )
    return out


def _rm_anova_by_hand(y: np.ndarray) -> tuple[float, int, int]:
    """One-way repeated-measures ANOVA, subjects x levels (the textbook sums of squares)."""
    n, k = y.shape
    grand = y.mean()
    ss_levels = n * ((y.mean(axis=0) - grand) ** 2).sum()
    ss_subjects = k * ((y.mean(axis=1) - grand) ** 2).sum()
    ss_error = ((y - grand) ** 2).sum() - ss_levels - ss_subjects
    df1, df2 = k - 1, (k - 1) * (n - 1)
    return (ss_levels / df1) / (ss_error / df2), df1, df2


def test_trials_give_the_confusion_rates_times_and_a_correct_anova():
    rng = np.random.default_rng(4)
    rates = rng.integers(0, 6, size=(10, 12)) / 5  # 10 participants, 5 presentations each
    trials = _trials(rates)
    a = analyse_trials(trials, "masked")
    assert a.trials == 600 and a.participants == [f"P{w:02d}" for w in range(10)]
    assert a.overall == pytest.approx(rates.mean())
    np.testing.assert_allclose(a.per_pattern, rates.mean(axis=0))
    assert a.response_times_s.mean() == pytest.approx(2.0 + 0.55 + 0.045)
    f, df1, df2 = _rm_anova_by_hand(rates)
    an = a.anova_pattern
    assert (an.ddof1, an.ddof2) == (df1, df2) == (11, 99)
    assert an.f == pytest.approx(f, rel=1e-6)
    assert 0 < an.p < 1 and an.participants == 10
    assert len(an.posthoc) == 66  # every pair of 12 patterns
    # One pair checked against a paired t-test computed here.
    pair = next(x for x in an.posthoc if (x["a"], x["b"]) == (0, 4))
    d = rates[:, 0] - rates[:, 4]
    t = d.mean() / (d.std(ddof=1) / np.sqrt(len(d)))
    assert pair["t"] == pytest.approx(t, rel=1e-6)
    assert a.anova_angle.ddof1 == 3


def test_an_incomplete_participant_is_left_out_of_the_anova_and_said_so(tmp_path):
    rates = np.tile(np.linspace(0.2, 1.0, 12), (3, 1))
    rates[1] = rates[1][::-1]
    trials = _trials(rates)
    trials += [t | {"participant": "late"} for t in trials[:10]]  # only pattern 0 and 1
    a = analyse_trials(trials, "masked")
    assert a.anova_pattern.participants == 3
    assert "1 participant(s) without every pattern left out" in a.anova_pattern.note
    paths = write_report([a], tmp_path)
    assert "Repeated-measures ANOVA across patterns" in paths["markdown"].read_text()


def test_no_variance_or_too_few_participants_is_reported_not_crashed():
    perfect = analyse_trials(_trials(np.ones((4, 12))), "masked")
    assert perfect.overall == 1.0
    assert perfect.anova_pattern.f is None and "no variance" in perfect.anova_pattern.note
    alone = analyse_trials(_trials(np.full((1, 12), 0.6)), "masked")
    assert alone.anova_pattern.f is None and "at least 2" in alone.anova_pattern.note
