"""What the robot acts on: fresh by the operator's clock, in order, once; the deadman's clock."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from common.clocks.clock_sync import ClockSync
from common.wire.messages import Command, Heartbeat
from robot_side.node.commands.command_gate import (
    FROM_FUTURE,
    PENDING,
    REPLAYED,
    STALE,
    STOP_BEFORE_RUN,
    STOP_PROOF_NS,
    STOP_PROVEN,
    STOP_UNPROVEN,
    UNPROVEN,
    UNSYNCED,
    WITHOUT_SESSION,
    CommandGate,
    RobotRun,
)

MS = 1_000_000
AGE = 250 * MS
OFFSET = 7_000 * MS  # the operator's clock minus ours
RUN = RobotRun(session=99, start_ns=50 * MS)  # this robot run: what operators echo


def _gate(synced: bool = True) -> CommandGate:
    clock = ClockSync()
    if synced:  # one exchange with zero delay: offset exactly OFFSET
        clock.add_sample(t1=0, t2=OFFSET, t3=OFFSET, t4=0)
    return CommandGate(clock, AGE)


def _cmd(
    seq: int, sent_local: int, action: str = "arm_jog", session: int = 5, echo: int | None = 99
) -> Command:
    velocity = (0.01, 0, 0, 0, 0, 0) if action == "arm_jog" else None
    return Command(
        seq=seq,
        t_send_ns=sent_local + OFFSET,
        action=action,
        velocity=velocity,
        session=session,
        echo_session=echo,
    )


def admit(gate: CommandGate, cmd: Command, t_recv: int, now: int):
    return gate.admit(cmd, t_recv, now, RUN)


def test_a_fresh_command_is_admitted_with_its_send_time_on_our_clock():
    gate = _gate()
    refusal, sent = admit(gate, _cmd(1, 1000 * MS), 1010 * MS, 1012 * MS)
    assert refusal is None and sent == 1000 * MS
    assert gate.last_fresh_ns == 1000 * MS


def test_a_command_older_than_the_age_limit_is_stale_but_a_stop_still_counts():
    gate = _gate()
    assert admit(gate, _cmd(1, 0), 300 * MS, 300 * MS)[0] == STALE
    assert admit(gate, _cmd(2, 1 * MS, "arm_stop"), 300 * MS, 300 * MS)[0] is None
    assert gate.last_fresh_ns is None  # neither kept the deadman alive


def test_before_the_clock_offset_only_commands_that_end_motion_are_admitted():
    gate = _gate(synced=False)
    assert admit(gate, _cmd(1, 0, "arm_jog"), 0, 0)[0] == UNSYNCED
    assert admit(gate, _cmd(2, 0, "gripper_close"), 0, 0)[0] == UNSYNCED
    assert admit(gate, _cmd(3, 0, "arm_stop"), 0, 0)[0] is None
    assert admit(gate, _cmd(4, 0, "gripper_hold"), 0, 0)[0] is None


def test_a_replay_in_the_same_session_is_refused_and_a_new_session_is_not():
    gate = _gate()
    first = _cmd(1, 100 * MS)
    assert admit(gate, first, 101 * MS, 101 * MS)[0] is None
    assert admit(gate, _cmd(2, 110 * MS), 111 * MS, 111 * MS)[0] is None
    assert admit(gate, first, 112 * MS, 112 * MS)[0] == REPLAYED  # an old seq
    same_seq_later = _cmd(2, 120 * MS)
    assert admit(gate, same_seq_later, 121 * MS, 121 * MS)[0] == REPLAYED
    assert admit(gate, _cmd(1, 130 * MS, session=6), 131 * MS, 131 * MS)[0] is None


def test_a_timestamp_from_the_future_neither_passes_nor_extends_the_deadman():
    gate = _gate()
    assert admit(gate, _cmd(1, 10_000 * MS), 100 * MS, 100 * MS)[0] == FROM_FUTURE
    refusal, sent = admit(gate, _cmd(2, 150 * MS), 100 * MS, 100 * MS)  # 50 ms ahead
    assert refusal is None and sent == 100 * MS  # clamped to arrival
    assert gate.last_fresh_ns == 100 * MS


@settings(max_examples=200, deadline=None)
@given(
    events=st.lists(
        st.tuples(
            st.integers(0, 5),  # seq
            st.integers(0, 2_000),  # send time, ms on our clock
            st.integers(0, 600),  # delay to arrival, ms
            st.sampled_from(["arm_jog", "arm_stop", "gripper_close"]),
        ),
        max_size=40,
    )
)
@pytest.mark.slow
def test_whatever_arrives_admitted_motion_is_fresh_ordered_and_the_deadman_never_leads(events):
    gate = _gate()
    last: tuple[int, int] | None = None
    now = 0
    for seq, sent_ms, delay_ms, action in events:
        t_recv = (sent_ms + delay_ms) * MS
        now = max(now, t_recv)
        refusal, sent = admit(gate, _cmd(seq, sent_ms * MS, action), t_recv, now)
        if refusal is None:
            # the boot's seq orders its commands (a stop's stamp may be unreadable)
            assert last is None or seq > last[0]
            last = (seq, sent_ms)
            if action != "arm_stop":
                assert now - sent <= AGE
        if gate.last_fresh_ns is not None:
            assert gate.last_fresh_ns <= now  # never a deadline set from the future


def _beat(seq: int, session: int = 5, echo: int | None = 99) -> Heartbeat:
    return Heartbeat(
        seq=seq, t_send_ns=seq * MS, node="operator", state="ok", session=session,
        echo_session=echo,
    )  # fmt: skip


def test_a_boot_is_believed_only_once_it_echoes_this_robot_run():
    gate = _gate()
    assert admit(gate, _cmd(1, 100 * MS, echo=42), 101 * MS, 101 * MS)[0] == UNPROVEN
    assert admit(gate, _cmd(2, 100 * MS, echo=None), 101 * MS, 101 * MS)[0] == UNPROVEN
    assert admit(gate, Command(seq=1, t_send_ns=0, action="arm_jog_end"), 0, 0)[0] == (
        WITHOUT_SESSION
    )
    assert gate.admit_signal(_beat(1, echo=42), RUN) == UNPROVEN
    assert gate.admit_signal(_beat(1), RUN) is None
    assert gate.admit_signal(_beat(1), RUN) == "heartbeats_replayed"
    # once a stream is set, a message of it is judged by its seq alone
    assert gate.admit_signal(_beat(2, echo=None), RUN) is None


def test_a_stop_that_cannot_be_believed_yet_is_pending_and_a_replayed_one_is_refused():
    gate = _gate()
    assert admit(gate, _cmd(3, 100 * MS, "arm_stop", echo=42), 101 * MS, 101 * MS)[0] == PENDING
    assert admit(gate, _cmd(4, 110 * MS, "arm_stop"), 111 * MS, 111 * MS)[0] is None
    assert admit(gate, _cmd(4, 110 * MS, "arm_stop"), 112 * MS, 112 * MS)[0] == REPLAYED


def test_a_pending_stop_latches_only_if_its_boot_proves_live_and_it_was_sent_in_this_run():
    gate = _gate()
    before = _cmd(1, 10 * MS, "arm_stop", echo=42)  # sent before this run started (50 ms)
    during = _cmd(2, 60 * MS, "arm_stop", echo=42)  # sent after, by an operator a beat behind
    dead = _cmd(9, 70 * MS, "arm_stop", session=8, echo=42)  # a boot that never proves
    for stop in (before, during, dead):
        assert admit(gate, stop, 80 * MS, 80 * MS)[0] == PENDING
        assert gate.judge_pending(stop, 80 * MS, 80 * MS, RUN) is None  # nothing proven yet
    assert gate.admit_signal(_beat(3), RUN) is None  # boot 5 now proves it hears this run
    assert gate.judge_pending(before, 80 * MS, 90 * MS, RUN) == STOP_BEFORE_RUN
    assert gate.judge_pending(during, 80 * MS, 90 * MS, RUN) == STOP_PROVEN
    assert gate.judge_pending(dead, 80 * MS, 90 * MS, RUN) is None
    assert gate.judge_pending(dead, 80 * MS, 81 * MS + STOP_PROOF_NS, RUN) == STOP_UNPROVEN


def test_a_stop_whose_stamp_is_unreadable_is_still_a_stop():
    gate = _gate()
    bad = Command(seq=1, t_send_ns=0, action="arm_stop", session=5, echo_session=99,
                  defects=("t_send_ns: command.t_send_ns is nan",))  # fmt: skip
    assert admit(gate, bad, 100 * MS, 100 * MS) == (None, None)
    no_seq = Command(seq=0, t_send_ns=5, action="arm_stop", session=5, echo_session=99,
                     defects=("seq: missing",))  # fmt: skip
    assert admit(gate, no_seq, 100 * MS, 100 * MS)[0] == PENDING  # the window cannot place it
