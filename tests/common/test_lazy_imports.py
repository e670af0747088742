"""A node imports up front what its threads would otherwise import mid-run (holding the lock)."""

from __future__ import annotations

import subprocess
import sys

PROBE = """
import sys
import numpy as np
from common.process.command_line import import_lazy_modules
import_lazy_modules()
before = set(sys.modules)
np.percentile(np.arange(100.0), [50, 99, 99.9])  # the status file's latency summary
print(sorted(set(sys.modules) - before))
"""


def test_a_latency_summary_imports_nothing_once_the_node_started():
    out = subprocess.run(
        [sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=60, check=True
    )
    assert out.stdout.strip() == "[]", (
        f"np.percentile imported {out.stdout.strip()} mid-run: add it to LAZY_MODULES"
    )
