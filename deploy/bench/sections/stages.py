"""Section: the latency budget, stage by stage, back to back and paced at the sensor's rate."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from deploy.bench.fmt import IMG_DIR, num, pyplot, results_of, save_figure, table
from deploy.bench.section import Context, Results, Section

TITLE = "Latency budget per stage"


@dataclass(frozen=True)
class StagesSizes:
    stage_frames: int  # back to back
    stage_paced_frames: int
    pace_hz: float  # the sensor's rate the paced runs wait for


SIZES = {
    "full": StagesSizes(stage_frames=20000, stage_paced_frames=1800, pace_hz=120.0),
    "quick": StagesSizes(stage_frames=2000, stage_paced_frames=300, pace_hz=120.0),
    "smallest": StagesSizes(stage_frames=100, stage_paced_frames=30, pace_hz=500.0),
}


def measure(ctx: Context, sizes: StagesSizes) -> dict[str, Any]:
    """Both runs; the paced medians and the loopback transit go to the context for others."""
    from deploy.bench.stages import stage_budget

    out = stage_budget(sizes.stage_frames, ctx.classifier)
    out["paced"] = stage_budget(sizes.stage_paced_frames, ctx.classifier, pace_hz=sizes.pace_hz)
    # the costs a frame pays in the field (paced), for the savings and the scale model
    ctx.stage_medians_us = {k: v["median_us"] for k, v in out["paced"]["stages"].items()}
    ctx.tcp_transit_us = out.get("transit", {}).get("tcp_loopback", {}).get("median_us", 0.0)
    return out


def markdown(results: Results) -> list[str]:
    s = results_of(results, "stages")
    if s is None:
        return ["", f"## {TITLE}", "", "Not run."]
    paced = s.get("paced") or {}
    pst = paced.get("stages", {})
    rate = paced.get("pace_hz")
    out = [
        "",
        f"## {TITLE}",
        "",
        f"Every frame is taken through the whole chain one at a time, so each stage meets "
        f"the caches the one before left. **Back to back**: {s['frames']:,} frames with no "
        f"pause. **Paced**: {num(paced.get('frames'))} frames at {num(rate, 0)} Hz, waiting "
        "between frames as the node waits for the sensor. Classifier backend "
        f"`{s['classifier_backend']}`, `{s['method']}` downsizing, `{s['order']}`. "
        "Microseconds, one core.",
        "",
    ]
    if s.get("compiled_step"):
        out += [
            "The node runs `frame_step` (one compiled call) where the plain path runs "
            "`sanitize_contact`, `classification` and `render`; frames alternate between the "
            "two, so each row has half the frames and both paths meet the same conditions. The "
            "plain rows are what `render.compiled_step = false` (or another classifier "
            "backend) costs; sums and totals below are the node's path.",
            "",
        ]
    out += table(
        [
            "stage",
            "back to back: median",
            "p99",
            f"paced at {num(rate, 0)} Hz: median",
            "p99",
            "what",
        ],
        [
            [
                f"`{k}`",
                num(v["median_us"]),
                num(v["p99_us"]),
                num(pst.get(k, {}).get("median_us")),
                num(pst.get(k, {}).get("p99_us")),
                v["what"],
            ]
            for k, v in s["stages"].items()
        ],
        "|---|---:|---:|---:|---:|---|",
    )
    tot = s["instrumented_total"]
    ptot = paced.get("instrumented_total", {})
    plain, pplain = s.get("instrumented_total_plain"), paced.get("instrumented_total_plain")
    plain_note = ""
    if plain and pplain:
        plain_note = (
            f" (the plain path's frames: median {num(plain['median_us'])} / p99 "
            f"{num(plain['p99_us'])} us back to back, median {num(pplain['median_us'])} / p99 "
            f"{num(pplain['p99_us'])} us paced)"
        )
    out += [
        "",
        f"Sum of the stage medians: {num(s['sum_of_stage_medians_us'])} us back to back, "
        f"{num(paced.get('sum_of_stage_medians_us'))} us paced; the instrumented chain end to "
        f"end: median {num(tot['median_us'])} / p99 {num(tot['p99_us'])} us back to back, "
        f"median {num(ptot.get('median_us'))} / p99 {num(ptot.get('p99_us'))} us paced"
        f"{plain_note}.",
        "",
        "**The same code costs several times more when frames are paced.** Between two "
        "frames the core runs other code (here other processes; on the robot PC the node's "
        "own threads), which evicts the caches and retrains the branch predictors an "
        "interpreter leans on (see Conditions: the first IK call after a frame period's gap "
        "costs many times a warm one, even when the gap spins on the same core). Back-to-back "
        "numbers are what a micro-benchmark shows; paced numbers are what a frame costs in "
        "the field, so the verdicts, the savings and the scale model below use them.",
        "",
        "One-way PUB to SUB in one process (a 204-byte message, back to back):",
        "",
    ]
    rows = []
    for name, t in (s.get("transit") or {}).items():
        if "error" in t:
            rows.append([name, "n/a", "n/a"])
        else:
            rows.append([name, num(t["median_us"]), num(t["p99_us"])])
    out += table(["transport", "median (us)", "p99 (us)"], rows, "|---|---:|---:|")
    out += ["", f"![stage budget]({IMG_DIR}/bench_stages.png)"]
    return out


def figure(result: dict[str, Any], path: Path) -> Path:
    plt = pyplot()
    names = list(result["stages"])
    paced = (result.get("paced") or {}).get("stages", {})
    series = [
        ("back to back, median", [result["stages"][n]["median_us"] for n in names], "#4c72b0"),
    ]
    if paced:
        rate = result["paced"]["pace_hz"]
        series.append(
            (
                f"paced {rate:g} Hz, median",
                [paced.get(n, {}).get("median_us", float("nan")) for n in names],
                "#dd8452",
            )
        )
        series.append(
            (
                f"paced {rate:g} Hz, p99",
                [paced.get(n, {}).get("p99_us", float("nan")) for n in names],
                "#f2c8a8",
            )
        )
    fig, ax = plt.subplots(figsize=(8.5, 5))
    h = 0.8 / len(series)
    for k, (label, values, color) in enumerate(series):
        ax.barh(
            [i - 0.4 + h * (k + 0.5) for i in range(len(names))],
            values,
            height=h,
            label=label,
            color=color,
        )
    ax.set_yticks(list(range(len(names))), names)
    ax.invert_yaxis()
    ax.set_xscale("log")
    ax.set_xlabel("microseconds (one core)")
    ax.set_title("latency budget per stage")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, axis="x", which="both")
    return save_figure(fig, path)


SECTION = Section(
    name="stages",
    title=TITLE,
    sizes=SIZES,
    measure=measure,
    markdown=markdown,
    figure=figure,
)
