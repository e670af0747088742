"""A roster changed while everything runs: SIGHUP, and relay and robot read it again.

Real processes (a CURVE relay, a robot on the UR simulator, operator nodes);
what moves the arm is read from the simulator.
"""

from __future__ import annotations

import signal
import threading
import time

import pytest
from fleet_monitor import Monitor, jog_for

from common.clock import now_ns
from harness.fleet import Fleet

pytestmark = [pytest.mark.slow, pytest.mark.timeout(180), pytest.mark.parallel]

JOG_X = [0.03, 0.0, 0.0, 0.0, 0.0, 0.0]


def _hang_up(fleet: Fleet, *names: str) -> None:
    for name in names:
        fleet.procs[name].popen.send_signal(signal.SIGHUP)


def _holder(monitor: Monitor, since_ns: int) -> bytes | str | None:
    """The lease holder in the newest robot heartbeat that arrived after ``since_ns``."""
    beats = [hb for t, hb in list(monitor.heartbeats) if t >= since_ns]
    return beats[-1].lease_holder if beats else "no heartbeat yet"


def test_a_key_added_may_take_control_and_a_key_removed_loses_it_and_stops_the_arm(
    tmp_path, arm_sim, quiet_gc
):
    fleet = Fleet(
        robots=["cell1"],
        operators={"a": "controller", "rec": "recorder", "obs": "observer"},
        workdir=tmp_path,
    )
    fleet.add_member("late", "controller")
    late_key = fleet.signing_key("late")
    with fleet:
        relay = fleet.start_relay()
        robot = fleet.start_robot("cell1", arm_sim.host)
        monitor = Monitor(fleet, "rec", ["cell1"])
        observer = Monitor(fleet, "obs", ["cell1"])
        try:
            fleet.wait_for(lambda: monitor.heartbeats, 60, "the robot's heartbeats")
            late = fleet.start_operator("late", "cell1", request_control=True, want_frames=False)
            fleet.wait_for(
                lambda: "CURVE handshake refused (operator)" in relay.log_text(),
                30,
                "the relay to refuse a key not in its roster",
            )
            assert monitor.holder_since(late_key, 0) is None

            # let it in: the same file for both, re-read on SIGHUP, nothing restarted
            everyone = {"a": "controller", "rec": "recorder", "obs": "observer"}
            fleet.rewrite_roster({**everyone, "late": "controller"})
            _hang_up(fleet, "relay", "cell1")
            fleet.wait_for(
                lambda: monitor.holder_since(late_key, 0) is not None, 30, "late's lease"
            )
            start = arm_sim.tcp_pose()[:3].copy()
            jog_for(late, JOG_X, 1.0)
            assert arm_sim.tcp_pose()[0] - start[0] > 0.01, "the added key moves the arm"

            # a broken file changes nothing
            fleet.roster.write_text("[[operator]]\nname = 3\n")
            _hang_up(fleet, "cell1")
            fleet.wait_for(
                lambda: "roster reload failed" in robot.log_text(), 10, "the failed reload"
            )
            start = arm_sim.tcp_pose()[:3].copy()
            jog_for(late, JOG_X, 0.5)
            assert arm_sim.tcp_pose()[0] - start[0] > 0.005, "still the holder"

            # nor does an empty one (it would remove every controller): refused, not obeyed
            good = fleet.roster.read_text()
            fleet.roster.write_text("")
            _hang_up(fleet, "cell1")
            fleet.wait_for(
                lambda: "would remove every robot (1) and every controller" in robot.log_text(),
                10,
                "the refused reload",
            )
            fleet.roster.write_text(good)
            start = arm_sim.tcp_pose()[:3].copy()
            jog_for(late, JOG_X, 0.5)
            assert arm_sim.tcp_pose()[0] - start[0] > 0.005, "still the holder after it"

            # late and obs removed, late while jogging: the lease goes, the arm stops, and
            # the relay cuts obs's open connection (everyone reconnects; obs is refused)
            jogging = threading.Thread(target=jog_for, args=(late, JOG_X, 4.0))
            jogging.start()
            time.sleep(1.0)
            fleet.rewrite_roster({"a": "controller", "rec": "recorder"})
            t_hup = now_ns()
            _hang_up(fleet, "relay", "cell1")
            fleet.wait_for(lambda: _holder(monitor, t_hup) is None, 5, "nobody holding")
            time.sleep(0.5)  # the stop, then what would move it if anything still did
            stopped_at = arm_sim.tcp_pose()[:3].copy()
            time.sleep(1.0)
            drift = abs(arm_sim.tcp_pose()[0] - stopped_at[0])
            jogging.join()
            assert drift < 1e-4, f"the arm moved {drift * 1000:.2f} mm after late was removed"
            reopened = lambda: "closing every connection" in relay.log_text()  # noqa: E731
            fleet.wait_for(reopened, 10, "the relay to close every connection")
            time.sleep(0.3)  # what was in flight when it closed has arrived
            t_cut = now_ns()
            time.sleep(1.0)
            assert any(t > t_cut for t, _ in list(monitor.heartbeats)), "rec reconnected"
            assert not any(t > t_cut for t, _ in list(observer.heartbeats)), "obs was cut off"
        finally:
            observer.close()
            monitor.close()
    stats = {name: p.stats() for name, p in fleet.procs.items()}
    assert stats["cell1"]["roster_reloads"] == 2, stats["cell1"]
    assert stats["cell1"]["roster_reloads_failed"] == 2, stats["cell1"]
    assert stats["cell1"]["messages_unknown_signer"] > 0, "late's messages after removal"
    assert stats["relay"]["roster_reloads"] == 2, stats["relay"]
    assert stats["relay"]["reopens"] == 1, stats["relay"]
    assert "late (controller) added" in robot.log_text()
    assert "late removed" in robot.log_text()
