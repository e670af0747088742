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

import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from harness.bench.command_path import RobotUnderCommands
from harness.headless_chromium import Chromium
from harness.operator_process import OperatorWithDashboard

WINDOW_S = 10.0
TICKS = os.sysconf("SC_CLK_TCK")


def cpu_s(pid: int) -> float:
    """User and system seconds of one process so far."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICKS


def tree_cpu_s(root: int) -> float:
    """``cpu_s`` of a process and every descendant alive now."""
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                ppid = int(f.read().rsplit(")", 1)[1].split()[1])
        except OSError:
            continue
        children.setdefault(ppid, []).append(int(entry))
    total, todo = 0.0, [root]
    while todo:
        pid = todo.pop()
        try:
            total += cpu_s(pid)
        except OSError:
            continue
        todo += children.get(pid, [])
    return total


def measure(push_rate_hz: float) -> None:
    workdir = Path(tempfile.mkdtemp(prefix="dxp-dashboard-cost-"))
    sets = (f"operator.dashboard.push_rate_hz={push_rate_hz}",)
    with (
        RobotUnderCommands(workdir) as rig,
        OperatorWithDashboard(workdir, rig.telemetry_endpoint, rig.command_endpoint, sets) as op,
    ):
        time.sleep(2.0)
        c0 = cpu_s(op.proc.pid)
        time.sleep(WINDOW_S)
        idle = (cpu_s(op.proc.pid) - c0) / WINDOW_S
        with Chromium(width=1280, height=1000) as page:
            page.navigate(op.url)
            page.wait_for("dxp.state.stimulus != null", 20)
            time.sleep(2.0)
            seq0 = page.evaluate("dxp.state.seq")
            c0, b0 = cpu_s(op.proc.pid), tree_cpu_s(page.proc.pid)
            time.sleep(WINDOW_S)
            node = (cpu_s(op.proc.pid) - c0) / WINDOW_S
            browser = (tree_cpu_s(page.proc.pid) - b0) / WINDOW_S
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
