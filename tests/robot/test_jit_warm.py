"""After the warm-up, a start loads every compiled function of the node from the cache."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest

pytestmark = pytest.mark.slow


def _warm() -> tuple[int, int]:
    run = [sys.executable, "-m", "robot_side.node.jit_warm"]
    out = subprocess.run(run, capture_output=True, text=True, timeout=300, check=True).stdout
    assert "classifier (numba), compiled frame step (mask mode), serial scan conversion" in out
    loaded, compiled = re.search(r"(\d+) loaded from the cache, (\d+) compiled", out).groups()
    return int(loaded), int(compiled)


def test_after_the_warm_up_a_start_compiles_nothing():
    first = _warm()  # make test has run it already: usually nothing to compile here either
    loaded, compiled = _warm()
    assert compiled == 0, (first, (loaded, compiled))
    assert loaded >= 4  # the classifier's two passes, the frame step, the scan conversion
