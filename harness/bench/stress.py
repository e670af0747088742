"""Numerical stress: nothing non-finite, nothing out of range, no jump, whatever comes in.

Three sweeps, each counting the outputs that are not finite (the goal is
zero) and the worst case of what must stay bounded:

- IK over a dense grid of the workspace and a thin shell inside its edge:
  angles and servo counts, and the largest round-trip error;
- random stimuli through the LinkGlideRenderer, with extreme, negative and
  non-finite values mixed in (the codec refuses them on the wire, but the
  renderer is the last line before the servos and must not need it): goal
  counts inside the calibrated limits, and the largest step per cycle;
- frames at the sensor floor, at saturation and beyond, and with
  non-finite taxels, through every rendering method and order and through
  the classifier: stimuli finite, within 0..9 N, at most one cell per row,
  and accepted by the wire codec.

As a bench section: numerical stress, every output finite and inside its limits whatever comes in.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from common.tactile.contract import FRAME_SHAPE, N_PATTERNS, SATURATION_N
from common.tactile.stimulus import METHODS, ORDERS, render_stimulus
from common.wire.codec import DecodeError, decode, encode
from common.wire.messages import Stimulus
from harness.bench.fmt import num, results_of, sci, table
from harness.bench.ik import edge_shell, reachable_mask, round_trip_mm, workspace_grid
from harness.bench.section import Context, Results, Section, Verdict
from operator_side.palm.linkglide import (
    DEFAULT_GEOMETRY,
    inverse_kinematics,
    inverse_kinematics_one,
)
from operator_side.palm.renderer import LinkGlideRenderer, RendererConfig
from operator_side.servos.calibration import COUNTS_PER_RAD, LinkGlideCalibration

log = logging.getLogger(__name__)

EXTREMES = np.array(
    [
        0.0,
        -0.0,
        1e-45,
        1e-38,
        0.5,
        0.999,
        1.0,
        1.0001,
        SATURATION_N - 0.001,
        SATURATION_N,
        SATURATION_N + 0.0001,
        1e6,
        3.4e38,
        -1.0,
        -3.4e38,
        np.nan,
        np.inf,
        -np.inf,
    ],
    dtype=np.float64,
)


def ik_stress(grid_step_mm: float, shell_points: int, seed: int = 6) -> dict[str, Any]:
    """Closed-form IK (vector and scalar) and counts over the grid and the edge shell."""
    g = DEFAULT_GEOMETRY
    cal = LinkGlideCalibration()
    grid = workspace_grid(grid_step_mm, g)
    inside, _ = edge_shell(grid_step_mm, shell_points, seed, g)
    shell = inside.reshape(-1, 2)
    shell = shell[reachable_mask(shell, g)]
    out: dict[str, Any] = {"grid_step_mm": grid_step_mm}
    for name, pts in (("grid", grid), ("shell", shell)):
        ang = inverse_kinematics(pts, g)
        err = round_trip_mm(pts, ang)
        blocks = ang[: (len(ang) // 3) * 3].reshape(-1, 3, 2)  # three linkages per call
        nonfinite_counts = 0
        for block in blocks[:: max(1, len(blocks) // 20000)]:
            c = cal.angles_to_counts(block)
            nonfinite_counts += int(not np.all(np.isfinite(c)))
        sub = pts[:: max(1, len(pts) // 20000)]
        scalar = np.array([inverse_kinematics_one(float(x), float(y), g) for x, y in sub])
        out[name] = {
            "points": len(pts),
            "nonfinite_angles": int((~np.isfinite(ang)).any(axis=1).sum()),
            "nonfinite_angles_scalar": int((~np.isfinite(scalar)).any(axis=1).sum()),
            "scalar_points": len(sub),
            "scalar_vs_vector_max_rad": float(
                np.abs(
                    np.pi - np.mod(np.pi - (scalar - inverse_kinematics(sub, g)), 2 * np.pi)
                ).max()
            ),
            "nonfinite_counts": nonfinite_counts,
            "fk_refused": int(np.isnan(err).sum()),
            "max_round_trip_mm": float(np.nanmax(err)),
        }
    return out


def _random_stimuli(n: int, rng: np.random.Generator) -> np.ndarray:
    """Half drawn from EXTREMES cell by cell, half plausible values with extremes sprinkled in."""
    a = rng.choice(EXTREMES, size=(n // 2, 3, 3))
    b = rng.uniform(-2.0, 12.0, size=(n - n // 2, 3, 3))
    spots = rng.random(b.shape) < 0.1
    b[spots] = rng.choice(EXTREMES, size=int(spots.sum()))
    out = np.concatenate([a, b])
    return out[rng.permutation(len(out))]


def renderer_stress(n: int, seed: int = 7) -> dict[str, Any]:
    """Random stimuli, one per palm step, through target_counts and the rate limiter."""
    cal = LinkGlideCalibration()
    renderer = LinkGlideRenderer(RendererConfig(), cal)
    rng = np.random.default_rng(seed)
    stimuli = _random_stimuli(n, rng)
    current = renderer.retract_counts.copy()
    nonfinite = out_of_limits = raised = 0
    largest_step = 0
    largest_target_jump = 0
    last_target = current
    for stim in stimuli:
        with np.errstate(invalid="ignore", over="ignore"):
            try:
                target = renderer.target_counts(stim)
            except Exception as e:  # any exception here would stop the operator node
                raised += 1
                log.error("renderer raised on %s: %s", stim.tolist(), e)
                continue
        nxt = renderer.step(current, target, 1.0)
        nonfinite += int(not np.all(np.isfinite(target)) or not np.all(np.isfinite(nxt)))
        out_of_limits += int(not cal.within_limits(target) or not cal.within_limits(nxt))
        largest_step = max(largest_step, int(np.abs(nxt - current).max()))
        largest_target_jump = max(largest_target_jump, int(np.abs(target - last_target).max()))
        current, last_target = nxt, target
    return {
        "stimuli": len(stimuli),
        "nonfinite_outputs": nonfinite,
        "out_of_limits": out_of_limits,
        "exceptions": raised,
        "largest_step_counts": largest_step,
        "largest_step_deg": largest_step / COUNTS_PER_RAD * 180 / np.pi,
        "max_step_counts_allowed": renderer.max_step_counts,
        "largest_target_jump_counts": largest_target_jump,
    }


def _stress_frames(rng: np.random.Generator, n_random: int) -> dict[str, np.ndarray]:
    shape = FRAME_SHAPE
    frames: dict[str, np.ndarray] = {
        "zeros": np.zeros(shape),
        "just_below_floor": np.full(shape, 0.999),
        "at_floor": np.full(shape, 1.0),
        "at_saturation": np.full(shape, SATURATION_N),
        "above_saturation": np.full(shape, SATURATION_N + 0.0001),
        "huge": np.full(shape, 3.4e38),
        "all_nan": np.full(shape, np.nan),
        "all_inf": np.full(shape, np.inf),
        "all_neg_inf": np.full(shape, -np.inf),
        "negative": np.full(shape, -5.0),
    }
    band = np.zeros(shape)
    band[:, 4:6, :] = SATURATION_N
    frames["saturated_row_band"] = band
    col = np.zeros(shape)
    col[:, :, 3] = 1.0
    frames["floor_column_band"] = col
    checker = np.where(np.indices(shape).sum(axis=0) % 2 == 0, SATURATION_N, 0.0)
    frames["checkerboard_saturated"] = checker
    nan_band = band.copy()
    nan_band[0, 5, 5] = np.nan
    frames["saturated_band_with_nan"] = nan_band
    for k in range(n_random):
        f = rng.choice(EXTREMES, size=shape)
        frames[f"random_extreme_{k}"] = f
    return frames


def rendering_stress(classifier: Any, n_random: int, seed: int = 8) -> dict[str, Any]:
    """Extreme frames through every method, order and mask; and through the classifier."""
    rng = np.random.default_rng(seed)
    frames = _stress_frames(rng, n_random)
    checked = nonfinite = out_of_range = two_in_row = codec_refused = raised = 0
    clf_nonfinite = clf_raised = 0
    for name, frame in frames.items():
        f32 = frame.astype(np.float32)
        for method in METHODS:
            for order in ORDERS:
                for pattern in (None, *range(N_PATTERNS)):
                    checked += 1
                    try:
                        with np.errstate(invalid="ignore", over="ignore"):
                            s = render_stimulus(f32, pattern, method=method, order=order)
                    except Exception as e:
                        raised += 1
                        log.error("render_stimulus raised on %s: %s", name, e)
                        continue
                    if not np.all(np.isfinite(s)):
                        nonfinite += 1
                        continue
                    out_of_range += int(s.min() < 0 or s.max() > SATURATION_N)
                    two_in_row += int(((s > 0).sum(axis=1) > 1).any())
                    msg = Stimulus(
                        seq=1,
                        t_send_ns=1,
                        t_capture_ns=1,
                        frame_seq=1,
                        mode="mask",
                        contact=bool(s.max() > 0),
                        stimulus=s,
                        pattern=pattern,
                    )
                    try:
                        decode(encode(msg))
                    except DecodeError:
                        codec_refused += 1
        if classifier is not None:
            from common.tactile.stimulus import sanitize_frame

            try:
                one = classifier.predict_one(sanitize_frame(f32))  # the node's call
                probs = (*one.angle_probs, *one.position_probs, one.confidence)
                clf_nonfinite += int(not all(math.isfinite(v) for v in probs))
            except Exception as e:
                clf_raised += 1
                log.error("classifier raised on %s: %s", name, e)
    return {
        "frames": len(frames),
        "renders_checked": checked,
        "nonfinite_outputs": nonfinite,
        "out_of_range": out_of_range,
        "more_than_one_cell_in_a_row": two_in_row,
        "refused_by_codec": codec_refused,
        "exceptions": raised,
        "classifier_nonfinite": clf_nonfinite,
        "classifier_exceptions": clf_raised,
        "named_frames": [k for k in frames if not k.startswith("random_extreme_")],
    }


def stress(
    classifier: Any, grid_step_mm: float, shell_points: int, n_stimuli: int, n_frames: int
) -> dict[str, Any]:
    ik = ik_stress(grid_step_mm, shell_points)
    rend = renderer_stress(n_stimuli)
    frames = rendering_stress(classifier, n_frames)
    total_nonfinite = (
        ik["grid"]["nonfinite_angles"]
        + ik["grid"]["nonfinite_angles_scalar"]
        + ik["grid"]["nonfinite_counts"]
        + ik["shell"]["nonfinite_angles"]
        + ik["shell"]["nonfinite_angles_scalar"]
        + ik["shell"]["nonfinite_counts"]
        + rend["nonfinite_outputs"]
        + frames["nonfinite_outputs"]
        + frames["classifier_nonfinite"]
    )
    return {
        "ik": ik,
        "renderer": rend,
        "rendering": frames,
        "total_nonfinite_outputs": total_nonfinite,
        "largest_round_trip_mm": max(
            ik["grid"]["max_round_trip_mm"], ik["shell"]["max_round_trip_mm"]
        ),
        "largest_servo_step_counts": rend["largest_step_counts"],
    }


TITLE = "Numerical stress"


@dataclass(frozen=True)
class StressSizes:
    stress_grid_mm: float
    stress_shell_points: int
    stress_stimuli: int  # random stimuli through the servo renderer
    stress_random_frames: int


SIZES = {
    "full": StressSizes(
        stress_grid_mm=0.05,
        stress_shell_points=40000,
        stress_stimuli=200000,
        stress_random_frames=500,
    ),
    "quick": StressSizes(
        stress_grid_mm=1.0, stress_shell_points=500, stress_stimuli=5000, stress_random_frames=10
    ),
    "smallest": StressSizes(
        stress_grid_mm=2.0, stress_shell_points=200, stress_stimuli=500, stress_random_frames=3
    ),
}


def measure(ctx: Context, sizes: StressSizes) -> dict[str, Any]:
    return stress(
        ctx.classifier,
        sizes.stress_grid_mm,
        sizes.stress_shell_points,
        sizes.stress_stimuli,
        sizes.stress_random_frames,
    )


def verdicts(results: Results) -> list[Verdict]:
    """Zero non-finite outputs: a check any machine must pass, not a timing."""
    st = results_of(results, "stress")
    return [
        Verdict(
            "numerical stress: zero non-finite outputs",
            None if st is None else f"{st['total_nonfinite_outputs']} non-finite",
            None if st is None else st["total_nonfinite_outputs"] == 0,
            table="check",
        )
    ]


def markdown(results: Results) -> list[str]:
    s = results_of(results, "stress")
    out = ["", f"## {TITLE}", ""]
    if s is None:
        return [*out, "Not run."]
    ik, rd, fr = s["ik"], s["renderer"], s["rendering"]
    out += table(
        ["sweep", "inputs", "non-finite outputs", "worst case"],
        [
            [
                f"IK, {ik['grid_step_mm']} mm workspace grid (vector; scalar on "
                f"{ik['grid']['scalar_points']:,})",
                num(ik["grid"]["points"]),
                num(
                    ik["grid"]["nonfinite_angles"]
                    + ik["grid"]["nonfinite_angles_scalar"]
                    + ik["grid"]["nonfinite_counts"]
                ),
                f"round trip {sci(ik['grid']['max_round_trip_mm'])} mm; scalar vs vector "
                f"{sci(ik['grid']['scalar_vs_vector_max_rad'])} rad",
            ],
            [
                "IK, shell inside the workspace edge",
                num(ik["shell"]["points"]),
                num(
                    ik["shell"]["nonfinite_angles"]
                    + ik["shell"]["nonfinite_angles_scalar"]
                    + ik["shell"]["nonfinite_counts"]
                ),
                f"round trip {sci(ik['shell']['max_round_trip_mm'])} mm; FK refused "
                f"{ik['shell']['fk_refused']}",
            ],
            [
                "random stimuli (extreme, negative, NaN, inf) through LinkGlideRenderer",
                num(rd["stimuli"]),
                num(rd["nonfinite_outputs"]),
                f"largest servo step {rd['largest_step_counts']} counts "
                f"({rd['largest_step_deg']:.2f} deg; limit {rd['max_step_counts_allowed']}); "
                f"out of limits {rd['out_of_limits']}; exceptions {rd['exceptions']}",
            ],
            [
                f"frames at floor, saturation, beyond, non-finite ({fr['frames']}) x methods x "
                "orders x masks",
                num(fr["renders_checked"]),
                num(fr["nonfinite_outputs"]),
                f"out of 0..9 N {fr['out_of_range']}; two cells in a row "
                f"{fr['more_than_one_cell_in_a_row']}; refused by the codec "
                f"{fr['refused_by_codec']}; exceptions {fr['exceptions']}; classifier "
                f"non-finite {fr['classifier_nonfinite']}",
            ],
        ],
        "|---|---:|---:|---|",
    )
    out += [
        "",
        f"Total non-finite outputs: **{s['total_nonfinite_outputs']}**. Largest round-trip "
        f"error: {sci(s['largest_round_trip_mm'])} mm. Largest servo step per cycle: "
        f"{s['largest_servo_step_counts']} counts ({_step_limit(rd['max_step_counts_allowed'])}).",
    ]
    return out


def _step_limit(counts: int) -> str:
    """The renderer's per-cycle limit as configured, and what it rounds to in whole counts."""
    import math

    from operator_side.palm.renderer import RendererConfig
    from operator_side.servos.calibration import COUNTS_PER_RAD

    configured = RendererConfig().max_step_deg_per_cycle
    return (
        f"{configured:g} deg rounds to {counts} counts, "
        f"{math.degrees(counts / COUNTS_PER_RAD):.2f} deg"
    )


SECTION = Section(
    name="stress",
    title=TITLE,
    sizes=SIZES,
    measure=measure,
    markdown=markdown,
    verdicts=verdicts,
)
