"""Two robots, five operator keys and a recorder through one relay, as real processes.

Every hop is CURVE, every operator signs, the robots connect out to the
relay. What moves an arm is read from the UR simulator's own state, not from
the nodes' counters.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import zmq
from fleet_monitor import Monitor, jog_for, kill_mid_jog_and_time_the_stop

from common.clock import now_ns
from common.codec import name_prefix
from common.security import SecurityConfig, client_options
from common.transport import Subscriber
from harness.fleet import Fleet
from operator_side.config import OperatorLinkConfig

pytestmark = [pytest.mark.slow, pytest.mark.parallel]

#: the fleet's operators keep the default: a stimulus older than this lifts the palm
OPERATOR_STALE_AFTER_MS = OperatorLinkConfig().stale_after_ms
JOG_X = [0.03, 0.0, 0.0, 0.0, 0.0, 0.0]  # the controllers jog along x
JOG_Y = [0.0, 0.03, 0.0, 0.0, 0.0, 0.0]  # the observers try y: it must never happen


def test_two_robots_five_operators_one_relay(tmp_path, arm_sims, quiet_gc):
    fleet = Fleet(
        robots=["cell1", "cell2"],
        operators={
            "c1": "controller",
            "c2": "controller",
            "obs1": "observer",
            "obs2": "observer",
            "rec": "recorder",
        },
        workdir=tmp_path,
    )
    with fleet:
        fleet.start_relay()
        for name, sim in zip(("cell1", "cell2"), arm_sims, strict=True):
            fleet.start_robot(name, sim.host)
        c1 = fleet.start_operator("c1", "cell1", request_control=True)
        c2 = fleet.start_operator("c2", "cell2", request_control=True)
        observers = [
            fleet.start_operator(o, r, want_frames=True)
            for o in ("obs1", "obs2")
            for r in ("cell1", "cell2")
        ]
        rec_proc = fleet.start_recorder("rec")
        monitor = Monitor(fleet, "rec", ["cell1", "cell2"])
        try:
            # the recorder starts last, below the nodes' priority: the scenario waits for it
            # to record both robots (a loaded run began without it and it saw 5 heartbeats)
            fleet.wait_for(
                lambda: all(
                    f"recording {r}_HBRT" in rec_proc.log_text() for r in ("cell1", "cell2")
                ),
                60,
                "the recorder's first heartbeat of each robot",
            )
            for c in ("c1", "c2"):
                key = fleet.signing_key(c)
                held = lambda k=key: monitor.holder_since(k, 0) is not None  # noqa: E731
                fleet.wait_for(held, 60, f"{c}'s lease")
            trips = arm_sims[0].stats()["watchdog_trips"]
            start = [sim.tcp_pose()[:3].copy() for sim in arm_sims]
            # The observers jog both robots along y; only cell1's controller jogs (along x).
            jogging = [threading.Thread(target=jog_for, args=(o, JOG_Y, 1.5)) for o in observers]
            for t in jogging:
                t.start()
            jog_for(c1, JOG_X, 1.0)
            for t in jogging:
                t.join()
            time.sleep(0.5)
            moved = [sim.tcp_pose()[:3] - s for sim, s in zip(arm_sims, start, strict=True)]
            assert abs(moved[0][1]) < 1e-3, f"cell1 moved along an observer's y: {moved[0]}"
            assert np.abs(moved[1]).max() < 1e-3, f"cell2 moved with no jog from c2: {moved[1]}"
            # a trip of the controller's watchdog stops the arm mid-jog: the robot node's kicks
            # stopped for the window, an unasked stop of the product (busy machine or not)
            tripped = arm_sims[0].stats()["watchdog_trips"] - trips
            assert moved[0][0] > 0.015 and not tripped, (
                f"cell1 did not follow its controller: {moved[0]} "
                f"(controller watchdog trips during the jog: {tripped})"
            )

            # Killing cell2's controller mid-jog stops that arm within the deadman.
            stop_ms = kill_mid_jog_and_time_the_stop(fleet, c2, arm_sims[1], JOG_X)
            # the deadman (250 ms) plus the stop's deceleration (0.03 m/s at 2 m/s^2: 15 ms),
            # the simulator's poll and the relay hop: inside the 400 ms stop budget
            assert stop_ms < 400, stop_ms
            print(f"cell2 stopped {stop_ms:.0f} ms after its controller died")
        finally:
            monitor.close()
        time.sleep(0.3)
    stats = {name: p.stats() for name, p in fleet.procs.items()}
    for name in ("obs1@cell1", "obs1@cell2", "obs2@cell1", "obs2@cell2", "c1@cell1"):
        s = stats[name]
        # the stream flowed (about 4 s at up to 60 Hz; the robot sends only the stimuli that
        # changed, so the count follows the scripted grasp: 116 to 174 seen) and every message
        # of it arrived (sequence numbers): PUB/SUB through the relay loses nothing on loopback
        assert s["stimuli_received"] > 20, (name, s)
        assert s["link_lost"] == 0 and s["decode_errors"] == 0, (name, s)
    rec = stats["rec"]
    # the recorder (started last, at a lower priority than the nodes, as deployed) records
    # every robot's stream from whenever it joined, and loses nothing of it: judged on the
    # robots' own sequence numbers, not on a window that the machine's speed sets
    for robot in ("cell1", "cell2"):
        for topic in ("STIM", "HBRT", "FRAM"):
            assert rec.get(f"{robot}_{topic}", 0) > 5, (robot, topic, rec)
            assert rec.get(f"{robot}_{topic}_lost", 0) == 0, (robot, topic, rec)
    assert rec.get("rejected", 0) == 0
    relay = stats["relay"]
    assert relay["commands_dropped_role"] > 0  # the observers' jogs stopped at the relay
    for robot in ("cell1", "cell2"):
        assert stats[robot]["lease_granted"] >= 1, stats[robot]
    assert stats["cell2"]["lease_expired"] == 1 and stats["cell2"]["deadman_trips"] >= 1


def test_hand_over_is_fast_loses_no_stimulus_and_moves_the_arm_for_the_new_holder_only(
    tmp_path, arm_sim, quiet_gc
):
    fleet = Fleet(
        robots=["cell1"],
        operators={"a": "controller", "b": "controller", "rec": "recorder"},
        workdir=tmp_path,
    )
    with fleet:
        fleet.start_relay()
        fleet.start_robot("cell1", arm_sim.host)
        a = fleet.start_operator("a", "cell1", request_control=True)
        b = fleet.start_operator("b", "cell1")
        monitor = Monitor(fleet, "rec", ["cell1"])
        key_a, key_b = fleet.signing_key("a"), fleet.signing_key("b")
        try:
            fleet.wait_for(lambda: monitor.holder_since(key_a, 0) is not None, 60, "a's lease")
            time.sleep(1.5)  # b's clock synced at the robot (its 2 Hz heartbeats echoed)
            t_req = now_ns()
            b.send({"action": "lease_request"})
            pending = lambda: any(  # noqa: E731
                t >= t_req and hb.lease_pending == key_b for t, hb in list(monitor.heartbeats)
            )
            fleet.wait_for(pending, 5, "b's request to show as pending")
            times = []
            t0 = now_ns()
            a.send({"action": "lease_grant", "grantee": key_b.hex()})
            fleet.wait_for(lambda: monitor.holder_since(key_b, t0) is not None, 5, "b's lease")
            times.append((monitor.holder_since(key_b, t0) - t0) / 1e6)
            # and back again, to measure twice
            time.sleep(0.3)
            t0 = now_ns()
            b.send({"action": "lease_grant", "grantee": key_a.hex()})
            fleet.wait_for(lambda: monitor.holder_since(key_a, t0) is not None, 5, "a's lease back")
            times.append((monitor.holder_since(key_a, t0) - t0) / 1e6)
            assert max(times) < 50, f"hand-over took {times} ms"
            # a holds it again: b's jogs (y) are refused by the robot itself, a's (x) move it
            start = arm_sim.tcp_pose()[:3].copy()
            jog_b = threading.Thread(target=jog_for, args=(b, JOG_Y, 1.0))
            jog_b.start()
            jog_for(a, JOG_X, 1.0)
            jog_b.join()
            time.sleep(0.3)
            moved = arm_sim.tcp_pose()[:3] - start
            assert moved[0] > 0.01 and abs(moved[1]) < 1e-3, moved
        finally:
            monitor.close()
    stats = {name: p.stats() for name, p in fleet.procs.items()}
    gap_ms = monitor.largest_stimulus_gap_ms()
    for name in ("a@cell1", "b@cell1"):
        s = stats[name]
        assert s["link_lost"] == 0 and s["stimuli_received"] > 100, (name, s)
        # a lift-off is the operator's staleness rule acting on a stream that paused over its
        # limit: on a hand-over the stream must not pause, busy machine or not
        assert s.get("lift_offs", 0) == 0, (
            f"{name}'s palm lifted off: the robot's stream paused (largest gap {gap_ms:.0f} ms "
            f"seen by the test's own relay client, staleness limit "
            f"{OPERATOR_STALE_AFTER_MS:.0f} ms); {s}"
        )
    robot = stats["cell1"]
    assert robot["lease_handed_over"] == 2 and robot["commands_not_controller"] > 5, robot
    print("hand-over times (ms):", [round(t, 1) for t in times])


def test_a_relay_that_lets_an_observer_command_still_cannot_move_the_arm(
    tmp_path, arm_sim, quiet_gc
):
    """The relay's roster says mallory may command; the robot's own roster says observer."""
    fleet = Fleet(
        robots=["cell1"],
        operators={"mallory": "observer", "rec": "recorder"},
        # the relay also lets in "eve", a key the robot has never heard of
        relay_roles={"mallory": "controller", "eve": "controller", "rec": "recorder"},
        workdir=tmp_path,
    )
    with fleet:
        fleet.start_relay()
        fleet.start_robot("cell1", arm_sim.host)
        mallory = fleet.start_operator("mallory", "cell1", request_control=True)
        eve = fleet.start_operator("eve", "cell1", request_control=True)
        monitor = Monitor(fleet, "rec", ["cell1"])
        try:
            fleet.wait_for(lambda: len(monitor.heartbeats) > 20, 60, "the robot's heartbeats")
            start = arm_sim.tcp_pose()[:3].copy()
            jog_eve = threading.Thread(target=jog_for, args=(eve, JOG_Y, 1.5))
            jog_eve.start()
            jog_for(mallory, JOG_X, 1.5)
            jog_eve.join()
            time.sleep(0.3)
            assert np.abs(arm_sim.tcp_pose()[:3] - start).max() < 1e-4
            assert all(hb.lease_holder is None for _, hb in monitor.heartbeats)
        finally:
            monitor.close()
    robot = fleet.procs["cell1"].stats()
    relay = fleet.procs["relay"].stats()
    assert relay.get("commands_dropped_role", 0) == 0  # the relay let everything through
    assert robot["lease_refused_role"] >= 1 and robot["commands_not_controller"] > 10, robot
    assert robot["messages_unknown_signer"] > 10, robot  # eve: every message ignored


def test_the_robot_skips_raw_frames_while_nobody_behind_the_relay_wants_them(tmp_path, quiet_gc):
    fleet = Fleet(
        robots=["cell1"],
        operators={"obs": "observer", "rec": "recorder"},
        workdir=tmp_path,
    )
    with fleet:
        fleet.start_relay()
        fleet.start_robot("cell1", None)
        fleet.start_operator("obs", "cell1", want_frames=False)
        monitor = Monitor(fleet, "rec", ["cell1"])

        def unwanted() -> float:
            hbs = [hb for _, hb in list(monitor.heartbeats) if hb.node == "robot"]
            return hbs[-1].stats.get("frames_unwanted", 0.0) if hbs else 0.0

        try:
            fleet.wait_for(lambda: unwanted() > 15, 60, "frames skipped for want of a subscriber")
            m = fleet.members["rec"]
            security = SecurityConfig(
                mode="curve",
                secret_key_file=m.curve_secret,
                server_public_key_file=fleet.members["relay"].curve_public,
            )
            ctx = zmq.Context()
            frames = Subscriber(
                ctx,
                fleet.ops_telemetry,
                bind=False,
                sock_opts=client_options(security),
                topics=(name_prefix(b"FRAM", b"cell1"),),
            )
            try:
                time.sleep(0.5)  # the subscription travels relay -> robot
                before = unwanted()
                got = 0
                end = time.monotonic() + 2.0
                while time.monotonic() < end:
                    if frames.poll(0.1):
                        got += len(frames.drain())
                during = unwanted() - before
            finally:
                frames.close()
                ctx.term()
            time.sleep(1.5)  # the unsubscription travels back
            after = unwanted() - before - during
        finally:
            monitor.close()
    assert got > 20, got  # 15 Hz for 2 s once someone asks
    assert during <= 2, during  # none skipped while wanted (the heartbeat's lag aside)
    assert after > 10, after  # and skipped again once nobody wants them


def test_a_client_written_from_the_protocol_doc_reads_one_named_robot_through_the_relay(
    tmp_path,
):
    """Raw pyzmq, msgpack and struct: topic, length byte, name, map (docs/protocol.md)."""
    import struct

    import msgpack

    fleet = Fleet(robots=["cell1", "cell10"], operators={"rec": "recorder"}, workdir=tmp_path)
    with fleet:
        fleet.start_relay()
        fleet.start_robot("cell1", None)
        fleet.start_robot("cell10", None)
        ctx = zmq.Context()
        sub = ctx.socket(zmq.SUB)
        sub.setsockopt(zmq.LINGER, 0)
        sub.setsockopt(zmq.RCVTIMEO, 200)
        sec = fleet.client_security("rec")
        for k, v in client_options(
            SecurityConfig(
                mode="curve",
                secret_key_file=sec["secret_key_file"],
                server_public_key_file=sec["server_public_key_file"],
            )
        ).items():
            sub.setsockopt(k, v)
        sub.connect(fleet.ops_telemetry)
        sub.setsockopt(zmq.SUBSCRIBE, b"STIM\x05cell1")  # not cell10: the length byte differs
        names, seen = set(), 0
        try:
            deadline = time.monotonic() + 60
            while seen < 30 and time.monotonic() < deadline:
                try:
                    data = sub.recv()
                except zmq.Again:
                    continue
                n = data[4]
                name, body = data[5 : 5 + n], msgpack.unpackb(data[5 + n :], raw=False)
                assert data[:4] == b"STIM" and body["v"] == 1 and body["type"] == "stimulus"
                assert len(struct.unpack("<9f", body["stimulus"])) == 9
                names.add(name)
                seen += 1
        finally:
            sub.close()
            ctx.term()
    assert seen == 30 and names == {b"cell1"}
