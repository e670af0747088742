"""A roster changed while everything runs on the fabric: SIGHUP, and router and robot read it.

Real processes (a router, a robot node, operator nodes). A key not in the
router's roster gets nothing through it; added, it may take the lease; a file
that would lock everyone out is refused and the roster in force stays;
removed, it loses the lease.
"""

from __future__ import annotations

import signal

import pytest
from fleet_monitor import Monitor

from common.clocks.clock import now_ns
from harness.fleet import Fleet

pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]


def _hang_up(fleet: Fleet, *names: str) -> None:
    for name in names:
        fleet.procs[name].popen.send_signal(signal.SIGHUP)


def _holder(monitor: Monitor, since_ns: int) -> bytes | str | None:
    beats = [hb for t, hb in list(monitor.heartbeats) if t >= since_ns]
    return beats[-1].lease_holder if beats else "no heartbeat yet"


def test_a_key_added_to_the_routers_roster_may_take_control_and_loses_it_when_removed(
    tmp_path, quiet_gc
):
    everyone = {"a": "controller", "rec": "recorder"}
    fleet = Fleet(robots=["cell1"], operators=dict(everyone), workdir=tmp_path)
    fleet.add_member("late", "controller")  # a certificate from the CA, but not in the roster
    late_key = fleet.signing_key("late")
    with fleet:
        router = fleet.start_router()
        fleet.start_robot("cell1", None)
        monitor = Monitor(fleet, "rec", ["cell1"])
        try:
            fleet.wait_for(lambda: monitor.heartbeats, 60, "the robot's heartbeats")
            late = fleet.start_operator("late", "cell1", request_control=True, want_frames=False)
            late.wait_ready(30)
            t0 = now_ns()
            fleet.wait_for(lambda: now_ns() - t0 > 2e9, 5, "two seconds")
            assert monitor.holder_since(late_key, 0) is None, "a key not in the roster got in"

            # let it in: the same file for router and robot, re-read on SIGHUP
            fleet.rewrite_roster({**everyone, "late": "controller"})
            _hang_up(fleet, "router", "cell1")
            fleet.wait_for(lambda: monitor.holder_since(late_key, 0) is not None, 30, "its lease")

            # a file that would remove every controller is refused at the router
            good = fleet.roster.read_text()
            fleet.roster.write_text("")
            _hang_up(fleet, "router")
            fleet.wait_for(
                lambda: "roster reload refused" in router.log_text(), 10, "the refused reload"
            )
            fleet.roster.write_text(good)
            t_kept = now_ns()
            fleet.wait_for(lambda: _holder(monitor, t_kept) == late_key, 10, "late still holding")

            # removed: the router takes its access away and the robot its lease
            fleet.rewrite_roster(everyone)
            t_hup = now_ns()
            _hang_up(fleet, "router", "cell1")
            fleet.wait_for(lambda: _holder(monitor, t_hup) is None, 10, "nobody holding")
        finally:
            monitor.close()
    status = fleet.procs["router"].log_text()
    assert status.count("roster reloaded") == 2, status[-2000:]
