"""The study's report: report.md with a table per mode, report.json, a confusion heatmap each.

What each number means is in docs/study.md; the numbers are
``operator_side.study.analysis``'s.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from common.tactile.contract import N_PATTERNS, pattern_name
from operator_side.study.analysis import Analysis


def _fmt(v: float | None, spec: str) -> str:
    """A number for the report; a t of infinity (no spread in a difference) is n/a."""
    return "n/a" if v is None else format(v, spec)


def _p(v: float | None) -> str:
    """A p-value; pingouin's 0 means below what a double can tell from 0."""
    if v is None:
        return "n/a"
    return "< 1e-15" if v == 0 else format(v, ".4g")


def p_text(v: float | None) -> str:
    """``= 0.0123`` or ``< 1e-15``, to follow a "p"."""
    text = _p(v)
    return text if text.startswith("<") or text == "n/a" else "= " + text


def _pct(v: float) -> str:
    return "n/a" if v is None or not math.isfinite(v) else f"{100 * v:.2f}%"


def confusion_figure(a: Analysis, path: Path) -> Path:
    """The proportions as a heatmap, annotated: rows rendered, columns answered."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    fig = Figure(figsize=(8.6, 7.2), dpi=110, layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    prop = np.nan_to_num(a.proportions)
    im = ax.imshow(prop, cmap="viridis", vmin=0, vmax=1)
    for r in range(N_PATTERNS):
        for c in range(N_PATTERNS):
            v = prop[r, c]
            if a.counts[r, c]:  # empty cells stay empty: the pattern of errors reads better
                ax.text(
                    c,
                    r,
                    f"{v:.2f}",
                    ha="center",
                    va="center",
                    fontsize=7,
                    color="black" if v > 0.6 else "white",
                )
    for d in range(N_PATTERNS):  # the right answers, outlined
        ax.add_patch(
            Rectangle((d - 0.5, d - 0.5), 1, 1, fill=False, edgecolor="white", linewidth=1.2)
        )
    labels = [f"{p} {pattern_name(p)}" for p in range(N_PATTERNS)]
    ax.set_xticks(range(N_PATTERNS), [str(p) for p in range(N_PATTERNS)])
    ax.set_yticks(range(N_PATTERNS), labels, fontsize=8)
    ax.set_xlabel("answered pattern")
    ax.set_ylabel("rendered pattern")
    who = f"{len(a.participants)} participants, " if a.participants else ""
    ax.set_title(
        f"{a.mode}: {who}{a.trials} trials; recognised {_pct(a.overall)}, "
        f"angle only {_pct(a.angle_only)}",
        fontsize=10,
    )
    fig.colorbar(im, ax=ax, fraction=0.046, pad=0.03, label="share of the row")
    fig.savefig(path, bbox_inches="tight")
    return path


def markdown(a: Analysis, figure: str | None) -> str:
    lines = [f"## Mode `{a.mode}`", ""]
    if a.participants:
        lines.append(f"{len(a.participants)} participant(s): {', '.join(a.participants)}.")
        lines.append("")
    rt = a.response_times_s
    lines += [
        "| measure | value |",
        "|---|---|",
        f"| trials | {a.trials} |",
        f"| recognition rate (pattern) | {_pct(a.overall)} ({a.correct} of {a.trials}) |",
        f"| mean of per-pattern rates (diagonal) | {_pct(a.diagonal_mean)} |",
        f"| recognition of the angle only | {_pct(a.angle_only)} |",
    ]
    if rt.size:
        sd = f", sd {rt.std(ddof=1):.2f} s" if rt.size > 1 else ""
        lines.append(
            f"| response time | mean {rt.mean():.2f} s{sd}, median {np.median(rt):.2f} s |"
        )
    lines.append("")
    lines += ["| pattern | name | recognised | mean response time |", "|---|---|---|---|"]
    for p in range(N_PATTERNS):
        rtp = a.rt_by_pattern[p]
        lines.append(
            f"| {p} | {pattern_name(p)} | {_pct(a.per_pattern[p])} | "
            f"{'–' if rtp is None else f'{rtp:.2f} s'} |"
        )
    lines.append("")
    if figure:
        lines += [f"![confusion matrix, {a.mode}]({figure})", ""]
    lines += ["Confusion matrix (share of each rendered pattern's presentations):", ""]
    lines.append("| rendered \\ answered | " + " | ".join(map(str, range(N_PATTERNS))) + " |")
    lines.append("|---" * (N_PATTERNS + 1) + "|")
    for r, row in enumerate(a.proportions):
        lines.append(f"| {r} | " + " | ".join(f"{v:.2f}" for v in np.nan_to_num(row)) + " |")
    lines.append("")
    for anova in (a.anova_pattern, a.anova_angle):
        if anova is None:
            continue
        lines.append(f"### Repeated-measures ANOVA across {anova.factor}s")
        lines.append("")
        if anova.f is None:
            lines += [f"Not computed: {anova.note}", ""]
            continue
        gg = "" if anova.p_gg is None else f", Greenhouse-Geisser p {p_text(anova.p_gg)}"
        lines.append(
            f"F({anova.ddof1:g}, {anova.ddof2:g}) = {anova.f:.3f}, p {p_text(anova.p)}{gg}, "
            f"generalised eta squared {anova.ng2:.3f}; {anova.participants} participants."
            + (f" {anova.note}" if anova.note else "")
        )
        lines.append("")
        sig = [x for x in anova.posthoc if x["significant"]]
        lines.append(
            f"Post-hoc paired t-tests: {len(sig)} of {len(anova.posthoc)} pairs at p < 0.05 "
            "uncorrected (as the paper reports), Holm-corrected p beside:"
        )
        lines.append("")
        if sig:
            lines += ["| pair | t | p | p (Holm) |", "|---|---|---|---|"]
            for x in sig:
                lines.append(
                    f"| {x['a']} vs {x['b']} | {_fmt(x['t'], '.3f')} | {_p(x['p'])} "
                    f"| {_p(x['p_holm'])} |"
                )
            lines.append("")
    for w in a.warnings:
        lines += [f"Note: {w}.", ""]
    return "\n".join(lines)


def write_report(analyses: list[Analysis], out_dir: Path, title: str = "") -> dict[str, Path]:
    """report.md, report.json and one confusion heatmap (PNG) per mode in ``out_dir``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths: dict[str, Path] = {}
    sections = []
    for a in analyses:
        png = confusion_figure(a, out_dir / f"confusion_{a.mode}.png")
        paths[f"confusion_{a.mode}"] = png
        sections.append(markdown(a, png.name))
    head = [
        f"# {title or 'DeepXPalm perception study'}",
        "",
        "Rows: the pattern rendered on the palm; columns: the participant's answer. "
        "Recognition: answers naming the rendered pattern. Angle only: answers with the "
        "right tilt, whatever the position. Response time: from the stimulus's onset on "
        "the palm to the answer. See docs/study.md for what each number means.",
        "",
    ]
    md = out_dir / "report.md"
    md.write_text("\n".join(head + sections))
    js = out_dir / "report.json"
    js.write_text(json.dumps({"analyses": [a.to_json() for a in analyses]}, indent=2) + "\n")
    paths.update(markdown=md, json=js)
    return paths
