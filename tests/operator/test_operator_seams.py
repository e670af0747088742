"""The operator node handed a clock and a capture link: driven without sockets or threads."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from common.clocks.clock import VirtualClock
from common.wire.messages import SESSION_LOW_MASK, Command, Heartbeat, Stimulus
from common.wire.transport import CaptureLink
from operator_side.node import OperatorNode
from operator_side.node.config import OperatorConfig
from operator_side.servos.in_memory import InMemoryServoBus


def _stimulus(seq: int, t_ns: int) -> Stimulus:
    return Stimulus(
        seq=seq,
        t_send_ns=t_ns,
        t_capture_ns=t_ns,
        frame_seq=seq,
        mode="direct",
        contact=True,
        stimulus=np.array([[0, 5, 0], [0, 5, 0], [0, 5, 0]], np.float32),
    )


def test_a_delivered_stimulus_moves_the_servos_in_virtual_time() -> None:
    clock = VirtualClock()
    link = CaptureLink()
    bus = InMemoryServoBus()
    bus.connect()
    node = OperatorNode(OperatorConfig(), bus, now=clock, link=link)
    period = round(1e9 / node.config.renderer.palm_step_rate_hz)
    link.deliver(_stimulus(1, clock()), clock())
    assert node.receive()
    assert node.last_stimulus is not None and node.last_stimulus.seq == 1
    node.palm_step(clock(), period)
    first = node.written_goals
    assert first is not None and first != node.renderer.retract_goals
    clock.advance(period)
    node.palm_step(clock(), period)  # still stepping toward the goal
    assert node.written_goals != first
    writes = node.counters["servo_writes"]
    node.rewrite_next()
    node.palm_step(clock(), period)
    assert node.counters["servo_writes"] == writes + 1
    stale = round(node.config.link.stale_after_ms * 1e6) + 1
    clock.advance(stale)
    node.palm_step(clock(), period)
    assert node.link_state == "stale"


def test_a_node_handed_a_link_refuses_to_run() -> None:
    node = OperatorNode(OperatorConfig(), InMemoryServoBus(), link=CaptureLink())
    with pytest.raises(RuntimeError, match="handed a link"):
        node.run(threading.Event())


def _robot_heartbeat(t_ns: int, stats: dict[str, float]) -> Heartbeat:
    return Heartbeat(seq=1, t_send_ns=t_ns, node="robot", state="ok", stats=stats)


def test_an_unconfirmed_gripper_command_is_sent_again_fresh_until_the_robot_names_it() -> None:
    clock = VirtualClock(t_ns=1_000_000_000)
    link = CaptureLink()
    node = OperatorNode(OperatorConfig(), InMemoryServoBus(), now=clock, link=link)
    confirm = round(node.config.link.gripper_confirm_ms * 1e6)
    node.send_command("gripper_close", grip_level=9)
    node.flush_commands(clock())
    first = [m for m in link.messages if isinstance(m, Command)]
    assert [(c.action, c.grip_level) for c in first] == [("gripper_close", 9)]
    clock.advance(confirm - 1)
    node.flush_commands(clock())
    assert len([m for m in link.messages if isinstance(m, Command)]) == 1, "not yet due"
    clock.advance(1)
    node.flush_commands(clock())
    sent = [m for m in link.messages if isinstance(m, Command)]
    assert len(sent) == 2 and node.counters["gripper_resent"] == 1
    assert sent[1].action == "gripper_close" and sent[1].grip_level == 9
    assert sent[1].seq > sent[0].seq and sent[1].t_send_ns > sent[0].t_send_ns, "a new command"
    session = float(sent[1].session & SESSION_LOW_MASK)
    # another session's confirmation is not ours; the robot naming our resend is
    other = {"gripper_command_seq": 99.0, "gripper_command_session": session + 1}
    link.deliver(_robot_heartbeat(clock(), other), clock())
    node.receive()
    assert node.counters["gripper_confirmed"] == 0
    ours = {"gripper_command_seq": float(sent[1].seq), "gripper_command_session": session}
    link.deliver(_robot_heartbeat(clock(), ours), clock())
    node.receive()
    assert node.counters["gripper_confirmed"] == 1
    clock.advance(10 * confirm)
    node.flush_commands(clock())
    assert len([m for m in link.messages if isinstance(m, Command)]) == 2, "confirmed: quiet"


def test_a_gripper_command_never_confirmed_is_counted_after_its_resends() -> None:
    clock = VirtualClock(t_ns=1_000_000_000)
    link = CaptureLink()
    node = OperatorNode(OperatorConfig(), InMemoryServoBus(), now=clock, link=link)
    confirm = round(node.config.link.gripper_confirm_ms * 1e6)
    node.send_command("gripper_open")
    for _ in range(10):
        node.flush_commands(clock())
        clock.advance(confirm)
    sent = [m for m in link.messages if isinstance(m, Command)]
    assert len(sent) == 1 + node.config.link.gripper_resends
    assert node.counters["gripper_unconfirmed"] == 1


def test_with_the_robots_key_only_its_signed_telemetry_reaches_the_palm(tmp_path) -> None:
    from common.wire.codec import SignatureError, decode, encode
    from common.wire.signing import Signer, generate_key_files, load_signer

    public, secret = generate_key_files(tmp_path, "cell1")
    robot, relay = load_signer(secret), Signer.generate()  # the relay holds no robot key
    clock = VirtualClock()
    link = CaptureLink()
    bus = InMemoryServoBus()
    bus.connect()
    config = OperatorConfig()
    config.link.robot_key_file = public
    node = OperatorNode(config, bus, now=clock, link=link)
    period = round(1e9 / node.config.renderer.palm_step_rate_hz)
    # forged on the path: validly signed, by the wrong key; and unsigned
    link.deliver(decode(encode(_stimulus(1, clock()), b"cell1", relay)), clock())
    link.deliver(_stimulus(2, clock()), clock())
    assert not node.receive()
    assert node.counters["telemetry_forged"] == 1 and node.counters["telemetry_unsigned"] == 1
    node.palm_step(clock(), period)
    assert node.last_stimulus is None
    assert node.written_goals in (None, node.renderer.retract_goals)  # the palm stays free
    # the robot's own, once a heartbeat of its run answered ours (test_telemetry_gate.py)
    node._send_heartbeat()
    echo = [m for m in link.messages if isinstance(m, Heartbeat)][-1].t_send_ns
    answer = Heartbeat(
        seq=1, t_send_ns=clock(), node="robot", state="ok", echo_t_send_ns=echo, session=7
    )
    link.deliver(decode(encode(answer, b"cell1", robot)), clock())
    stimulus = _stimulus(3, clock())
    stimulus.session = 7
    wire = encode(stimulus, b"cell1", robot)
    link.deliver(decode(wire), clock())
    assert node.receive() and node.last_stimulus.seq == 3
    node.palm_step(clock(), period)
    assert node.written_goals != node.renderer.retract_goals
    # and its bytes cannot be altered on the way: the stimulus cells are signed too
    tampered = bytearray(wire)
    cells = wire.rindex(b"\xa1x\xc4\x24") + 4  # x (the stimulus), then bin8's header: the cells
    tampered[cells + 4] ^= 0x01
    with pytest.raises(SignatureError):
        decode(bytes(tampered))


def _stops(link: CaptureLink) -> list[Command]:
    return [m for m in link.messages if isinstance(m, Command) and m.action == "arm_stop"]


def test_a_stop_is_sent_again_until_the_robot_shows_it_latched() -> None:
    clock = VirtualClock(t_ns=1_000_000_000)
    link = CaptureLink()
    node = OperatorNode(OperatorConfig(), InMemoryServoBus(), now=clock, link=link)
    every = round(node.config.link.stop_resend_ms * 1e6)
    node.send_command("arm_stop")
    node.flush_commands(clock())
    clock.advance(every - 1)
    node.flush_commands(clock())
    assert len(_stops(link)) == 1, "not yet due"
    clock.advance(1)
    node.flush_commands(clock())
    clock.advance(every)
    node.flush_commands(clock())
    stops = _stops(link)
    assert len(stops) == 3 and node.counters["stops_resent"] == 2
    assert stops[2].seq > stops[1].seq > stops[0].seq, "each a new command"
    # a heartbeat that says nothing of the latch confirms nothing; one that shows it set does
    link.deliver(_robot_heartbeat(clock(), {"gripper_command_seq": 0.0}), clock())
    node.receive()
    clock.advance(every)
    node.flush_commands(clock())
    assert len(_stops(link)) == 4
    link.deliver(_robot_heartbeat(clock(), {"arm_stop_latched": 1.0}), clock())
    node.receive()
    clock.advance(10 * every)
    node.flush_commands(clock())
    assert len(_stops(link)) == 4 and node.counters["stops_confirmed"] == 1


def test_a_resume_ends_the_stops_resending_and_an_unlatched_stop_gives_up() -> None:
    clock = VirtualClock(t_ns=1_000_000_000)
    link = CaptureLink()
    node = OperatorNode(OperatorConfig(), InMemoryServoBus(), now=clock, link=link)
    every = round(node.config.link.stop_resend_ms * 1e6)
    node.send_command("arm_stop")
    node.flush_commands(clock())
    node.send_command("arm_resume")  # before the robot showed the latch: no stop after it
    node.flush_commands(clock())
    for _ in range(5):
        clock.advance(every)
        node.flush_commands(clock())
    actions = [m.action for m in link.messages if isinstance(m, Command)]
    assert actions == ["arm_stop", "arm_resume"]
    node.send_command("arm_stop")  # never shown latched (a recorder's key): given up on
    for _ in range(
        round(node.config.link.stop_resend_for_ms / node.config.link.stop_resend_ms) + 5
    ):
        node.flush_commands(clock())
        clock.advance(every)
    assert node.counters["stops_unconfirmed"] == 1
    resent = len(_stops(link)) - 2
    assert 0 < resent <= node.config.link.stop_resend_for_ms / node.config.link.stop_resend_ms
