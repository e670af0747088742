"""The study's analysis, as the paper reports it: confusion, recognition, time, ANOVA.

Over every participant's test trials in one mode:

- the 12 x 12 confusion matrix (rows: the pattern rendered, columns: the
  answer), as counts and as proportions of each row;
- the overall recognition rate: correct answers over trials (with every
  pattern presented equally often, the mean of the matrix's diagonal, which
  is how the paper's 9.67% and 82.5% come out of its Tables I and II);
- recognition of the angle only (the answer's tilt right, its position
  ignored: the paper's 28%);
- response times (from the stimulus's onset on the palm to the answer);
- a single-factor repeated-measures ANOVA of each participant's recognition
  rate across the 12 patterns, with post-hoc paired t-tests between every
  pair (pingouin, as the paper), uncorrected as the paper reports them and
  Holm-corrected beside them; the same across the 4 angles.

A confusion matrix alone (a published table) gives every rate but no ANOVA,
which needs each participant's answers. The report (markdown, JSON, the
heatmaps) is ``operator_side.study.report``'s.
"""

from __future__ import annotations

import csv
import logging
import math
import warnings
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from common.errors import ConfigError
from common.tactile.contract import N_ANGLES, N_PATTERNS, classes_of
from operator_side.study.protocol import read_records

log = logging.getLogger(__name__)

ANGLE_OF = np.array([classes_of(p)[0] for p in range(N_PATTERNS)])
SAME_ANGLE = ANGLE_OF[:, None] == ANGLE_OF[None, :]


@dataclass
class Anova:
    factor: str  # "pattern" or "angle"
    f: float | None
    ddof1: float | None
    ddof2: float | None
    p: float | None
    p_gg: float | None  # Greenhouse-Geisser corrected, when pingouin gives it
    ng2: float | None  # generalised eta squared
    participants: int
    note: str = ""
    posthoc: list[dict[str, Any]] = field(default_factory=list)  # every pair


@dataclass
class Analysis:
    """The numbers of one rendering mode; JSON-able through ``to_json``."""

    mode: str
    source: str  # "trials" or "confusion matrix"
    participants: list[str]
    counts: np.ndarray  # (12, 12) int: rows rendered, columns answered
    response_times_s: np.ndarray  # every test trial's, or empty for a matrix
    rt_by_pattern: list[float | None]
    anova_pattern: Anova | None = None
    anova_angle: Anova | None = None
    warnings: list[str] = field(default_factory=list)

    @property
    def trials(self) -> int:
        return int(self.counts.sum())

    @property
    def correct(self) -> int:
        return int(np.trace(self.counts))

    @property
    def proportions(self) -> np.ndarray:
        rows = self.counts.sum(axis=1, keepdims=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(rows > 0, self.counts / np.maximum(rows, 1), np.nan)

    @property
    def per_pattern(self) -> np.ndarray:
        return np.diag(self.proportions)

    @property
    def overall(self) -> float:
        """Correct answers over trials."""
        return self.correct / self.trials if self.trials else math.nan

    @property
    def diagonal_mean(self) -> float:
        """Mean of the per-pattern rates: equals ``overall`` when presentations are balanced."""
        return float(np.nanmean(self.per_pattern)) if self.trials else math.nan

    @property
    def angle_only(self) -> float:
        return float(self.counts[SAME_ANGLE].sum() / self.trials) if self.trials else math.nan

    @property
    def angle_counts(self) -> np.ndarray:
        """(4, 4): rendered angle by answered angle."""
        out = np.zeros((N_ANGLES, N_ANGLES), dtype=np.int64)
        for a in range(N_ANGLES):
            for b in range(N_ANGLES):
                out[a, b] = self.counts[np.ix_(a == ANGLE_OF, b == ANGLE_OF)].sum()
        return out

    def to_json(self) -> dict[str, Any]:
        rt = self.response_times_s
        return {
            "mode": self.mode,
            "source": self.source,
            "participants": self.participants,
            "trials": self.trials,
            "correct": self.correct,
            "recognition_rate": _num(self.overall),
            "recognition_rate_diagonal_mean": _num(self.diagonal_mean),
            "angle_only_rate": _num(self.angle_only),
            "per_pattern_rate": [_num(v) for v in self.per_pattern],
            "response_time_s": None
            if rt.size == 0
            else {
                "mean": _num(rt.mean()),
                "sd": _num(rt.std(ddof=1)) if rt.size > 1 else None,
                "median": _num(np.median(rt)),
                "by_pattern_mean": [_num(v) for v in self.rt_by_pattern],
            },
            "confusion_counts": self.counts.tolist(),
            "confusion_proportions": [[_num(v) for v in row] for row in self.proportions],
            "angle_confusion_counts": self.angle_counts.tolist(),
            "anova_pattern": None if self.anova_pattern is None else asdict(self.anova_pattern),
            "anova_angle": None if self.anova_angle is None else asdict(self.anova_angle),
            "warnings": self.warnings,
        }


def _num(v: Any, digits: int = 6) -> float | None:
    if v is None:
        return None
    v = float(v)
    return None if not math.isfinite(v) else round(v, digits)


# ------------------------------------------------------------------- input
def find_result_files(paths: Iterable[Path]) -> list[Path]:
    """Files as given, and every ``*.jsonl`` in a directory given."""
    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            out.extend(sorted(p.glob("*.jsonl")))
        elif p.exists():
            out.append(p)
        else:
            raise ConfigError(f"{p} does not exist")
    if not out:
        raise ConfigError("no results files (*.jsonl) found")
    return out


def load_test_trials(paths: Iterable[Path]) -> list[dict[str, Any]]:
    """Every test-phase trial record, checked: practice trials are never analysed."""
    trials = []
    for path in find_result_files(paths):
        for rec in read_records(path):
            if rec.get("kind") != "trial" or rec.get("phase") != "test":
                continue
            try:
                p, a = int(rec["pattern"]), int(rec["answer"])
                rt = float(rec["response_time_s"])
                ok = 0 <= p < N_PATTERNS and 0 <= a < N_PATTERNS and str(rec["participant"])
            except (KeyError, TypeError, ValueError):
                ok = False
            if not ok:
                log.warning("%s: skipping a malformed trial record %r", path, rec)
                continue
            trials.append({**rec, "pattern": p, "answer": a, "response_time_s": rt})
    return trials


def read_confusion_csv(path: Path, presentations_per_row: int | None = None) -> np.ndarray:
    """A 12 x 12 matrix from CSV (``#`` comments, an optional header row and label column).

    Counts are taken as they are. Proportions (every row sums to 1) need
    ``presentations_per_row`` and must be whole numbers of presentations:
    a published table rounded to other values cannot be a real count.
    """
    rows = []
    with Path(path).open(newline="") as f:
        for row in csv.reader(line for line in f if not line.lstrip().startswith("#")):
            if not row or not any(c.strip() for c in row):
                continue
            try:
                values = [float(c) for c in row]
            except ValueError:
                continue  # a header
            rows.append(values[-N_PATTERNS:] if len(values) > N_PATTERNS else values)
    m = np.array(rows, dtype=np.float64)
    if m.shape != (N_PATTERNS, N_PATTERNS):
        raise ConfigError(f"{path}: expected a 12 x 12 matrix, found {m.shape}")
    if np.any(m < 0) or not np.all(np.isfinite(m)):
        raise ConfigError(f"{path}: values must be finite and non-negative")
    if np.allclose(m.sum(axis=1), 1.0, atol=1e-6):
        if presentations_per_row is None:
            raise ConfigError(
                f"{path} holds proportions: say how many presentations each row is "
                "(--presentations; the paper: 10 participants x 5 = 50)"
            )
        counts = m * presentations_per_row
        if not np.allclose(counts, np.rint(counts), atol=1e-6):
            raise ConfigError(
                f"{path}: proportions x {presentations_per_row} are not whole presentations"
            )
        return np.rint(counts).astype(np.int64)
    if not np.allclose(m, np.rint(m)):
        raise ConfigError(f"{path}: neither counts (whole numbers) nor row proportions")
    return np.rint(m).astype(np.int64)


# ---------------------------------------------------------------- analysis
def analyse_confusion(counts: np.ndarray, mode: str = "table") -> Analysis:
    counts = np.asarray(counts, dtype=np.int64)
    if counts.shape != (N_PATTERNS, N_PATTERNS):
        raise ValueError(f"a confusion matrix is 12 x 12, not {counts.shape}")
    a = Analysis(
        mode=mode,
        source="confusion matrix",
        participants=[],
        counts=counts,
        response_times_s=np.zeros(0),
        rt_by_pattern=[None] * N_PATTERNS,
    )
    a.warnings.append("a confusion matrix alone has no per-participant data: no ANOVA")
    return a


def analyse_trials(trials: list[dict[str, Any]], mode: str, alpha: float = 0.05) -> Analysis:
    """One mode's trials (other modes' are ignored) over every participant."""
    trials = [t for t in trials if t.get("mode") == mode]
    if not trials:
        raise ConfigError(f"no test trials in mode {mode!r}")
    counts = np.zeros((N_PATTERNS, N_PATTERNS), dtype=np.int64)
    for t in trials:
        counts[t["pattern"], t["answer"]] += 1
    rts = np.array([t["response_time_s"] for t in trials], dtype=np.float64)
    pats = np.array([t["pattern"] for t in trials])
    participants = sorted({str(t["participant"]) for t in trials})
    a = Analysis(
        mode=mode,
        source="trials",
        participants=participants,
        counts=counts,
        response_times_s=rts,
        rt_by_pattern=[
            float(rts[pats == p].mean()) if np.any(pats == p) else None for p in range(N_PATTERNS)
        ],
    )
    per_row = counts.sum(axis=1)
    if per_row.min() != per_row.max():
        a.warnings.append(
            f"patterns were presented unequally ({per_row.min()} to {per_row.max()} times): "
            "the overall rate and the diagonal mean differ"
        )
    a.anova_pattern = repeated_measures(trials, "pattern", alpha)
    a.anova_angle = repeated_measures(trials, "angle", alpha)
    return a


def repeated_measures(trials: list[dict[str, Any]], factor: str, alpha: float) -> Anova:
    """Each participant's recognition rate per level, then pingouin's RM-ANOVA and t-tests.

    Only participants who met every level are kept (listwise, as the
    ANOVA requires); the note says how many were left out.
    """
    levels = N_PATTERNS if factor == "pattern" else N_ANGLES
    hits: dict[str, np.ndarray] = {}
    seen: dict[str, np.ndarray] = {}
    for t in trials:
        who = str(t["participant"])
        if factor == "pattern":
            level, ok = t["pattern"], t["answer"] == t["pattern"]
        else:
            level = classes_of(t["pattern"])[0]
            ok = classes_of(t["answer"])[0] == level
        hits.setdefault(who, np.zeros(levels))[level] += ok
        seen.setdefault(who, np.zeros(levels))[level] += 1
    complete = sorted(w for w in seen if np.all(seen[w] > 0))
    left_out = len(seen) - len(complete)
    note = f"{left_out} participant(s) without every {factor} left out. " if left_out else ""
    empty = Anova(factor, None, None, None, None, None, None, len(complete))
    if len(complete) < 2:
        empty.note = note + "needs at least 2 participants who met every level"
        return empty
    rates = np.array([hits[w] / seen[w] for w in complete])
    if np.allclose(rates, rates[0, 0]):
        empty.note = note + "every rate is the same: no variance to test"
        return empty
    import pandas as pd  # pingouin's own dependency; loaded only for the ANOVA
    import pingouin as pg

    df = pd.DataFrame(
        [
            {"participant": w, factor: level, "rate": rates[i, level]}
            for i, w in enumerate(complete)
            for level in range(levels)
        ]
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # degenerate sphericity tests with few participants
        aov = pg.rm_anova(data=df, dv="rate", within=factor, subject="participant", detailed=False)
        post = pg.pairwise_tests(
            data=df, dv="rate", within=factor, subject="participant", padjust="holm"
        )
    row = aov.iloc[0]
    pairs = []
    for _, r in post.iterrows():
        p_unc = _col(r, "p_unc", "p-unc")
        t = _col(r, "T")
        pairs.append(
            {
                "a": int(r["A"]),
                "b": int(r["B"]),
                # every participant's difference the same: t is infinite, not a number
                "t": None if t is None or abs(t) > 1e9 else t,
                "dof": _col(r, "dof"),
                "p": p_unc,
                "p_holm": _col(r, "p_corr", "p-corr"),
                "significant": p_unc is not None and p_unc < alpha,
            }
        )
    return Anova(
        factor=factor,
        f=_col(row, "F"),
        ddof1=_col(row, "ddof1", "DF"),
        ddof2=_col(row, "ddof2"),
        p=_col(row, "p_unc", "p-unc"),
        p_gg=_col(row, "p_GG_corr", "p-GG-corr"),
        ng2=_col(row, "ng2"),
        participants=len(complete),
        note=note.strip(),
        posthoc=pairs,
    )


def _col(row: Any, *names: str) -> float | None:
    """A number from a pingouin result row; column names changed across versions."""
    for name in names:
        if name in row.index:
            return _num(row[name])
    return None
