"""The nodes' link over a real router: what each kind of message gets, and what a key may do.

The robot's and operator's ends are the product's own ``FabricPublisher`` and
``FabricSubscriber`` over real Zenoh sessions (QUIC, mutual TLS) to a real
router made from the roster; the attacker is a session opened with one
member's legitimate certificate.
"""

from __future__ import annotations

import time

import pytest
from tests_support import stimulus, wait_until

from common.fabric import keyexprs
from common.fabric.link import STOP_COPIES, FabricPublisher, FabricSubscriber
from common.wire.codec import MAX_MESSAGE_BYTES, encode
from common.wire.messages import Command, Heartbeat, Stimulus

pytestmark = [pytest.mark.slow, pytest.mark.untimed, pytest.mark.timeout(120)]

#: how long a message that would arrive has to arrive on loopback, however busy the machine
ARRIVES_S = 5.0
#: how long to watch for a message that must not arrive (a refused one would come in ms)
REFUSED_S = 1.0


def _operator_inbox(site, member: str, robot: str = "cell1", frames: bool = True):
    keys = keyexprs.Wanted(frames=frames).keys(robot)
    return FabricSubscriber(site.session(member), keys, expect_name=robot.encode())


def _robot_inbox(site, robot: str = "cell1", member: str | None = None):
    kinds = ("command", keyexprs.STOP, "heartbeat")
    keys = tuple(keyexprs.robot_inbox_for(robot, k) for k in kinds)
    return FabricSubscriber(site.session(member or robot), keys, expect_name=robot.encode())


def _collect(sub: FabricSubscriber, seconds: float, until=None) -> list:
    got: list = []
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        if sub.poll(0.05):
            got.extend(m for m, _ in sub.drain())
            if until is not None and until(got):
                break
    return got


def _settle(pub: FabricPublisher, kind: str = "stimulus") -> None:
    """Wait until the router has told the publisher someone listens (a subscription's
    declaration travels a round trip)."""
    assert wait_until(lambda: pub._pubs[kind].matching_status.matching, ARRIVES_S)


def test_a_robots_stimuli_reach_an_operator_and_only_the_newest_waits(site):
    inbox = _operator_inbox(site, "alice")
    robot = FabricPublisher(site.session("cell1"), robot=b"cell1", operator=None)
    _settle(robot)
    for seq in range(1, 51):  # 200 a second (within the router's gate), never drained meanwhile
        if seq == 50:
            time.sleep(0.05)  # the last past the gate's interval, however busy the machine
        robot.send(stimulus(seq=seq))
        time.sleep(0.005)
    time.sleep(0.5)
    got = [m for m in _collect(inbox, ARRIVES_S, until=lambda g: g) if isinstance(m, Stimulus)]
    # one slot per latest-value key: a backlog never turns into lag
    assert [m.seq for m in got] == [50]
    assert inbox.counters["superseded"] >= 1


def test_a_stop_arrives_once_though_it_travels_with_copies(site):
    inbox = _robot_inbox(site, "cell2")
    alice = FabricPublisher(site.session("alice"), robot=b"cell2", operator="alice")
    _settle(alice, keyexprs.STOP)
    stop = Command(seq=7, t_send_ns=time.time_ns(), action="arm_stop", session=1)
    alice.send(stop)
    got = _collect(inbox, ARRIVES_S, until=lambda g: g)
    time.sleep(0.3)
    got += [m for m, _ in inbox.drain()]
    assert [(type(m), m.action, m.seq) for m in got] == [(Command, "arm_stop", 7)]
    assert inbox.counters["stop_copies_dropped"] <= STOP_COPIES
    assert alice.sent == 1


def test_another_keys_stops_never_make_a_late_copy_count_again(site):
    """Each sender's stops are remembered apart: an observer's flood of stops (each its own
    payload) leaves alice's late copy of her stop known as a copy, not a second stop."""
    inbox = _robot_inbox(site, "cell1")
    alice = FabricPublisher(site.session("alice"), robot=b"cell1", operator="alice")
    olga = FabricPublisher(site.session("olga"), robot=b"cell1", operator="olga")
    _settle(alice, keyexprs.STOP)
    _settle(olga, keyexprs.STOP)
    stop = alice.send(Command(seq=3, t_send_ns=time.time_ns(), action="arm_stop", session=5))
    first = _collect(inbox, ARRIVES_S, until=lambda g: g)
    flood = 3 * 32  # three times what one sender's memory holds
    for seq in range(1, flood + 1):  # at half the rate the router's gate for stops passes
        olga.send(Command(seq=seq, t_send_ns=time.time_ns(), action="arm_stop", session=9))
        time.sleep(0.02)
    got = _collect(inbox, ARRIVES_S, until=lambda g: len(g) >= flood)
    # a busy machine bunches two sends inside the gate's interval now and then (95 of 96 once):
    # what matters is that far more than one memory's worth came between
    assert len(got) >= 2 * 32, f"{len(got)} of the observer's {flood} stops arrived"
    alice.send_raw(stop, keyexprs.STOP)  # the same stop again: copies held up on the way
    late = _collect(inbox, REFUSED_S)
    assert [(m.action, m.seq) for m in first] == [("arm_stop", 3)]
    assert late == [], [(m.action, m.seq) for m in late]


def test_a_robot_key_cannot_put_under_another_robots_name(site):
    inbox = _operator_inbox(site, "alice", robot="cell2")
    forger = site.session("cell1")
    for kind in ("stimulus", "heartbeat"):
        key = keyexprs.robot_key("cell2", kind)
        for _ in range(5):
            forger.put(key, encode(stimulus(seq=99), b"cell2"))
    assert _collect(inbox, REFUSED_S) == []


def test_no_key_reads_what_its_role_may_not(site):
    heard: list[str] = []
    cell1 = site.session("cell1")
    mallory = site.session("mallory")
    rec = site.session("rec")
    subs = [
        cell1.declare_subscriber("dxp/cell2/op/*/*", lambda s: heard.append(f"cell1 {s.key_expr}")),
        mallory.declare_subscriber("dxp/**", lambda s: heard.append(f"mallory {s.key_expr}")),
        mallory.declare_subscriber(
            "dxp/cell2/op/alice/command", lambda s: heard.append(f"mallory {s.key_expr}")
        ),
        rec.declare_subscriber("dxp/cell2/op/**", lambda s: heard.append(f"rec {s.key_expr}")),
    ]
    robot = _robot_inbox(site, "cell2")
    alice = FabricPublisher(site.session("alice"), robot=b"cell2", operator="alice")
    _settle(alice, "command")
    for seq in range(1, 6):  # 50 a second, as a jogging page sends
        alice.send(Command(seq=seq, t_send_ns=time.time_ns(), action="gripper_open", session=1))
        time.sleep(0.02)
    # the robot reads them (a busy machine may bunch two inside the router's rate gate)
    assert _collect(robot, ARRIVES_S, until=lambda g: len(g) >= 5)
    time.sleep(0.3)
    assert heard == []
    for sub in subs:
        sub.undeclare()


def test_an_operator_puts_only_under_its_own_name_and_role(site):
    robot = _robot_inbox(site, "cell1")
    mallory = site.session("mallory")  # an observer
    rec = site.session("rec")  # a recorder
    command = Command(seq=1, t_send_ns=time.time_ns(), action="arm_resume", session=5)
    data = encode(command, b"cell1")
    mallory.put(keyexprs.operator_key("cell1", "mallory", "command"), data)  # not an observer's
    mallory.put(keyexprs.operator_key("cell1", "alice", "command"), data)  # not her name
    rec.put(keyexprs.operator_key("cell1", "rec", keyexprs.STOP), data)  # a recorder puts nothing
    rec.put(keyexprs.operator_key("cell1", "rec", "heartbeat"), data)
    assert _collect(robot, REFUSED_S) == []
    # what an observer may put does arrive: a stop
    stop = Command(seq=2, t_send_ns=time.time_ns(), action="arm_stop", session=5)
    observer = FabricPublisher(mallory, robot=b"cell1", operator="mallory")
    _settle(observer, keyexprs.STOP)
    observer.send(stop)
    got = _collect(robot, ARRIVES_S, until=lambda g: g)
    assert [(m.action, m.seq) for m in got] == [("arm_stop", 2)]


def test_a_payload_over_the_codecs_limit_never_crosses_the_router(site):
    robot = _robot_inbox(site, "cell2")
    alice = site.session("alice")
    key = keyexprs.operator_key("cell2", "alice", "heartbeat")
    pub = alice.declare_publisher(key)
    assert wait_until(lambda: pub.matching_status.matching, ARRIVES_S)
    hb = Heartbeat(seq=1, t_send_ns=time.time_ns(), node="operator", state="ok", session=3)
    small = encode(hb, b"cell2")
    pub.put(small + b"\x00" * (MAX_MESSAGE_BYTES + 1 - len(small)))  # one byte over
    # then valid ones, 20 a second, until one arrives: on a busy machine two puts can reach
    # the router within its rate gate's interval, however far apart they were sent
    got: list = []
    t_end = time.monotonic() + ARRIVES_S
    while not got and time.monotonic() < t_end:
        time.sleep(0.05)
        pub.put(small)
        got += [m for m, _ in robot.drain()]
    time.sleep(0.3)
    got += [m for m, _ in robot.drain()]
    assert got and {type(m) for m in got} == {Heartbeat}
    assert robot.rejected_total == 0  # the oversized one never reached the robot to be refused


def test_a_flood_on_one_key_is_gated_per_peer_and_the_others_flow(site):
    robot = _robot_inbox(site, "cell1")
    mallory = site.session("mallory")
    key = keyexprs.operator_key("cell1", "mallory", keyexprs.STOP)
    flood = mallory.declare_publisher(key)
    assert wait_until(lambda: flood.matching_status.matching, ARRIVES_S)
    alice = FabricPublisher(site.session("alice"), robot=b"cell1", operator="alice")
    _settle(alice, "command")
    t0 = time.monotonic()
    n = sent = 0
    next_command = t0
    while time.monotonic() - t0 < 1.0:  # as fast as Python puts: tens of thousands a second
        flood.put(b"junk" + n.to_bytes(4, "big"))
        n += 1
        if time.monotonic() >= next_command:  # alice's commands, 20 a second
            sent += 1
            alice.send(
                Command(seq=sent, t_send_ns=time.time_ns(), action="gripper_open", session=9)
            )
            next_command += 0.05
    got = _collect(robot, 2.0)
    commands = [m for m in got if isinstance(m, Command)]
    # the other key's commands all arrived: reliable, never gated at the router (bunched
    # behind the flood's hold on this process's interpreter lock, they still pass), queued
    # apart from the flood's stops at the robot
    assert len(commands) == sent, (len(commands), sent)
    # the junk passed at most at the stop gate's rate (100/s for one peer): far below n
    refused = robot.rejected_total
    assert n > 2000 and refused <= 200, (n, refused)
