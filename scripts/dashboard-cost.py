"""What one open dashboard page costs the operator's PC, at a given push rate.

    python scripts/dashboard-cost.py [PUSH_RATE_HZ ...]   # default: 30 60

For each rate: the robot node on its simulators and the operator node with its
dashboard, each its own process as deployed (the rig the browser tests use),
then a headless chromium with the page open. Over 10 s with no page and 10 s
with it, prints the CPU seconds per second of the operator node's process and
of the browser's processes (all of chromium's), and the states the page drew
per second. The robot's scripted grasp keeps the stimulus, the frame and the
linkages moving, so every push slot has something new to draw.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from harness.bench.command_path import RobotUnderCommands
from harness.headless_chromium import Chromium
from harness.operator_process import OperatorWithDashboard
from harness.processes import cpu_s, in_session, process_cpu_s

WINDOW_S = 10.0


def browser_cpu_s(page: Chromium) -> float:
    """CPU seconds of every process of the browser's session (it starts in one of its own)."""
    return sum(cpu_s(pid) or 0.0 for pid in in_session(page.proc.pid))


def measure(push_rate_hz: float) -> None:
    workdir = Path(tempfile.mkdtemp(prefix="dxp-dashboard-cost-"))
    sets = (f"operator.dashboard.push_rate_hz={push_rate_hz}",)
    with (
        RobotUnderCommands(workdir) as rig,
        OperatorWithDashboard(workdir, rig.telemetry_endpoint, rig.command_endpoint, sets) as op,
    ):
        time.sleep(2.0)
        c0 = process_cpu_s(op.proc.pid)
        time.sleep(WINDOW_S)
        idle = (process_cpu_s(op.proc.pid) - c0) / WINDOW_S
        with Chromium(width=1280, height=1000) as page:
            page.navigate(op.url)
            page.wait_for("dxp.state.stimulus != null", 20)
            time.sleep(2.0)
            seq0 = page.evaluate("dxp.state.seq")
            c0, b0 = process_cpu_s(op.proc.pid), browser_cpu_s(page)
            time.sleep(WINDOW_S)
            node = (process_cpu_s(op.proc.pid) - c0) / WINDOW_S
            browser = (browser_cpu_s(page) - b0) / WINDOW_S
            drawn = (page.evaluate("dxp.state.seq") - seq0) / WINDOW_S
    print(
        f"push_rate_hz {push_rate_hz:g}: operator node {idle:.2f} CPU s/s with no page, "
        f"{node:.2f} with one; the page's browser {browser:.2f}; {drawn:.1f} states/s"
    )


def main(argv: list[str]) -> int:
    for rate in [float(a) for a in argv] or [30.0, 60.0]:
        measure(rate)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
