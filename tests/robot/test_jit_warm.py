"""The warm-up compiles the node's numba code into the cache a robot node then loads."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

pytestmark = [pytest.mark.slow, pytest.mark.parallel]


def test_the_warm_up_fills_the_cache_each_part_of_the_node_loads(tmp_path):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    run = [sys.executable, "-m", "robot_side.jit_warm"]
    out = subprocess.run(run, env=env, capture_output=True, text=True, timeout=300, check=True)
    assert "classifier (numba), compiled frame step (mask mode), serial scan conversion" in (
        out.stdout
    )
    cached = {p.name.split(".")[1].split("-")[0] for p in tmp_path.rglob("*.nbi")}
    assert {"classify_frame", "_forward_batch", "_frame_step", "convert_scan"} <= cached, cached
