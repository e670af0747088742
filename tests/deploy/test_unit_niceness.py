"""A child started at its unit's Nice=: the process, and its session's group when it leads one."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from deploy.unit_policy import set_niceness

GROUP = Path("/proc/self/autogroup")  # absent on a kernel without sched_autogroup
REPORT = (
    "import os, pathlib; g = pathlib.Path('/proc/self/autogroup');"
    "print(os.nice(0), g.read_text().split()[-1] if g.exists() else 'none')"
)


def _child(nice: int, new_session: bool) -> tuple[int, str]:
    out = subprocess.run(
        [sys.executable, "-c", REPORT],
        capture_output=True,
        text=True,
        timeout=30,
        start_new_session=new_session,
        preexec_fn=lambda: set_niceness(nice),
    )
    process, group = out.stdout.split()
    return int(process), group


def test_a_session_leader_gets_the_units_niceness_for_its_group_too():
    process, group = _child(-3, new_session=True)
    if os.geteuid() == 0:
        assert (process, group) in ((-3, "-3"), (-3, "none"))
    else:  # not permitted to raise it: the same program at the priority it had
        assert process == os.nice(0) and group in ("0", "none")


def test_a_child_in_its_parents_session_leaves_the_sessions_group_alone():
    mine = GROUP.read_text().split()[-1] if GROUP.exists() else "none"
    process, group = _child(os.nice(0) + 1, new_session=False)  # lowering needs no privilege
    assert process == os.nice(0) + 1
    assert group == mine
