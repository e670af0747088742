"""How much each section measures: the presets behind ``--quick`` and ``--size``.

``full`` is for the committed report on a quiet machine; ``quick`` is a
one-minute look; ``smallest`` exists so a test can run every section in
seconds and keep the code from rotting (its numbers mean nothing).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

SECTIONS = (
    "stages",
    "e2e_inproc",
    "e2e_tcp",
    "downsizing",
    "classifier",
    "ik",
    "skipping",
    "scale",
    "stress",
    "node_cpu",
    "command_path",
    "video",
    "netsim",
)


@dataclass(frozen=True)
class Sizes:
    """How many repetitions each section takes; the presets trade time for tighter tails."""

    stage_frames: int
    e2e_frames: int
    pace_hz: float
    stage_paced_frames: int
    e2e_paced_frames: int
    tcp_frames: int
    tcp_rate_hz: float
    ds_repeats: int
    ds_calls: int
    clf_calls: int
    clf_paced_calls: int
    clf_eval_repeats: int
    clf_randomized_repeats: int
    clf_backends_default: tuple[str, ...]
    clf_backends_others: tuple[str, ...]
    ik_grid_mm: float
    ik_shell_points: int
    ik_numeric_points: int
    ik_calls: int
    ik_least_squares: bool
    skip_cycles: float
    stress_grid_mm: float
    stress_shell_points: int
    stress_stimuli: int
    stress_random_frames: int
    node_warmup_s: float
    node_measure_s: float
    cmd_flood_messages: int  # command_path: jogs in the flood
    cmd_cost_messages: int  # command_path: messages timed through the intake
    scale_rates: tuple[float, ...]
    scale_measured: bool
    scale_backends: tuple[str | None, ...]
    video_frames: int = 1200  # glass-to-glass: stamped frames read in the browser (40 s)
    netsim_seconds: float = 20.0  # per scenario, 100 messages a second
    netsim_scenarios: tuple[str, ...] = (
        "none",
        "lan",
        "metro",
        "intercontinental",
        "loopback_trace",
    )


ALL_BACKENDS = ("numba", "numpy", "onnxruntime", "torchscript", "torch")
PRESETS: dict[str, Sizes] = {
    "full": Sizes(
        stage_frames=20000,
        e2e_frames=20000,
        pace_hz=120.0,
        stage_paced_frames=1800,
        e2e_paced_frames=2400,
        tcp_frames=3000,
        tcp_rate_hz=120.0,
        ds_repeats=8,
        ds_calls=20000,
        clf_calls=5000,
        clf_paced_calls=600,
        clf_eval_repeats=4,
        clf_randomized_repeats=8,
        clf_backends_default=ALL_BACKENDS,
        clf_backends_others=("numba", "onnxruntime"),
        ik_grid_mm=0.05,
        ik_shell_points=20000,
        ik_numeric_points=2000,
        ik_calls=5000,
        ik_least_squares=True,
        skip_cycles=2.0,
        stress_grid_mm=0.05,
        stress_shell_points=40000,
        stress_stimuli=200000,
        stress_random_frames=500,
        node_warmup_s=5.0,
        node_measure_s=20.0,
        cmd_flood_messages=100000,
        cmd_cost_messages=20000,
        scale_rates=(120.0, 500.0, 1000.0),
        scale_measured=True,
        scale_backends=(None, "onnxruntime", "numpy"),
    ),
    "quick": Sizes(
        stage_frames=2000,
        e2e_frames=2000,
        pace_hz=120.0,
        stage_paced_frames=300,
        e2e_paced_frames=300,
        tcp_frames=400,
        tcp_rate_hz=200.0,
        ds_repeats=2,
        ds_calls=2000,
        clf_calls=1000,
        clf_paced_calls=150,
        clf_eval_repeats=1,
        clf_randomized_repeats=1,
        clf_backends_default=("numba", "numpy", "onnxruntime"),  # torch costs 10 s to load
        clf_backends_others=("numba",),
        ik_grid_mm=0.5,
        ik_shell_points=2000,
        ik_numeric_points=100,
        ik_calls=1000,
        ik_least_squares=True,
        skip_cycles=0.5,
        stress_grid_mm=0.5,
        stress_shell_points=2000,
        stress_stimuli=20000,
        stress_random_frames=30,
        node_warmup_s=4.0,
        node_measure_s=6.0,
        cmd_flood_messages=30000,
        cmd_cost_messages=5000,
        scale_rates=(120.0, 500.0, 1000.0),
        scale_measured=False,
        scale_backends=(None,),
        video_frames=300,
        netsim_seconds=5.0,
    ),
    "smallest": Sizes(
        stage_frames=100,
        e2e_frames=100,
        pace_hz=500.0,
        stage_paced_frames=30,
        e2e_paced_frames=30,
        tcp_frames=50,
        tcp_rate_hz=500.0,
        ds_repeats=1,
        ds_calls=100,
        clf_calls=50,
        clf_paced_calls=10,
        clf_eval_repeats=1,
        clf_randomized_repeats=0,
        clf_backends_default=("numba", "numpy", "onnxruntime"),
        clf_backends_others=(),
        ik_grid_mm=2.0,
        ik_shell_points=200,
        ik_numeric_points=10,
        ik_calls=50,
        ik_least_squares=False,
        skip_cycles=0.05,
        stress_grid_mm=2.0,
        stress_shell_points=200,
        stress_stimuli=500,
        stress_random_frames=3,
        node_warmup_s=3.0,
        node_measure_s=2.0,
        cmd_flood_messages=2000,
        cmd_cost_messages=500,
        scale_rates=(120.0, 500.0, 1000.0),
        scale_measured=False,
        scale_backends=(None,),
        video_frames=30,
        netsim_seconds=1.0,
        netsim_scenarios=("none",),
    ),
}


def sizes_for(preset: str, **changes: Any) -> Sizes:
    """A preset with some fields changed (tests)."""
    return replace(PRESETS[preset], **changes)
