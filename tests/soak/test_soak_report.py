"""The soak's measuring parts, quickly: /proc readings, growth figures, the recording scan."""

from __future__ import annotations

import os

import numpy as np

from common.recording.mcap_recorder import McapRecorder
from harness import processes, soak


def test_proc_readings_of_this_process():
    assert processes.rss_mb(os.getpid()) > 1
    assert processes.cpu_s(os.getpid()) > 0
    assert processes.rss_mb(2**22 + 7) is None  # no such process: None, not an exception
    assert processes.cpu_s(2**22 + 7) is None


def test_growth_is_measured_after_start_up_and_as_a_slope():
    s = soak.Series(pid=1)
    for i in range(61):
        t = i * 10.0
        s.samples.append((t, 50.0 + (0 if t < 30 else 0.01 * t), t * 0.2))
    r = s.report(startup_s=30, warmup_s=120)
    assert r["growth_mb"] == round(0.01 * 600 - 0.01 * 30, 2)
    assert abs(r["slope_after_warmup_mb_per_hour"] - 36.0) < 0.01
    assert abs(r["cpu_percent"] - 20.0) < 0.01


def test_scan_counts_non_finite_values_and_out_of_limit_goals(tmp_path):
    path = tmp_path / "operator.mcap"
    with McapRecorder(path) as rec:
        rec.write(
            "operator/servo_goals",
            1,
            {"counts": np.array([2048, 2048, 2048, 2048, 2048, 4000]), "angles": np.zeros(6)},
        )
        rec.write("operator/link", 2, {"state": "ok", "x": float("nan")})
    out = soak.scan_recording(path)
    assert out["records"] == 2
    assert out["servo_goals_out_of_limits"] == 1
    assert out["nonfinite_values"] == 1
    assert out["link_state_share"] == {"ok": 1.0}
