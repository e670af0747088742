"""What the robot acts on: fresh by the operator's clock, in order, once; the deadman's clock."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from common.clock_sync import ClockSync
from common.messages import Command
from robot_side.command_gate import (
    FROM_FUTURE,
    REPLAYED,
    STALE,
    UNSYNCED,
    CommandGate,
)

pytestmark = pytest.mark.parallel

MS = 1_000_000
AGE = 250 * MS
OFFSET = 7_000 * MS  # the operator's clock minus ours


def _gate(synced: bool = True) -> CommandGate:
    clock = ClockSync()
    if synced:  # one exchange with zero delay: offset exactly OFFSET
        clock.add_sample(t1=0, t2=OFFSET, t3=OFFSET, t4=0)
    return CommandGate(clock, AGE)


def _cmd(seq: int, sent_local: int, action: str = "arm_jog", session: int = 5) -> Command:
    velocity = (0.01, 0, 0, 0, 0, 0) if action == "arm_jog" else None
    return Command(
        seq=seq, t_send_ns=sent_local + OFFSET, action=action, velocity=velocity, session=session
    )


def test_a_fresh_command_is_admitted_with_its_send_time_on_our_clock():
    gate = _gate()
    refusal, sent = gate.admit(_cmd(1, 1000 * MS), 1010 * MS, 1012 * MS)
    assert refusal is None and sent == 1000 * MS
    assert gate.last_fresh_ns == 1000 * MS


def test_a_command_older_than_the_age_limit_is_stale_but_a_stop_still_counts():
    gate = _gate()
    assert gate.admit(_cmd(1, 0), 300 * MS, 300 * MS)[0] == STALE
    assert gate.admit(_cmd(2, 1 * MS, "arm_stop"), 300 * MS, 300 * MS)[0] is None
    assert gate.last_fresh_ns is None  # neither kept the deadman alive


def test_before_the_clock_offset_only_commands_that_end_motion_are_admitted():
    gate = _gate(synced=False)
    assert gate.admit(_cmd(1, 0, "arm_jog"), 0, 0)[0] == UNSYNCED
    assert gate.admit(_cmd(2, 0, "gripper_close"), 0, 0)[0] == UNSYNCED
    assert gate.admit(_cmd(3, 0, "arm_stop"), 0, 0)[0] is None
    assert gate.admit(_cmd(4, 0, "gripper_hold"), 0, 0)[0] is None


def test_a_replay_in_the_same_session_is_refused_and_a_new_session_is_not():
    gate = _gate()
    first = _cmd(1, 100 * MS)
    assert gate.admit(first, 101 * MS, 101 * MS)[0] is None
    assert gate.admit(_cmd(2, 110 * MS), 111 * MS, 111 * MS)[0] is None
    assert gate.admit(first, 112 * MS, 112 * MS)[0] == REPLAYED  # an old seq
    same_seq_later = _cmd(2, 120 * MS)
    assert gate.admit(same_seq_later, 121 * MS, 121 * MS)[0] == REPLAYED
    assert gate.admit(_cmd(1, 130 * MS, session=6), 131 * MS, 131 * MS)[0] is None


def test_a_timestamp_from_the_future_neither_passes_nor_extends_the_deadman():
    gate = _gate()
    assert gate.admit(_cmd(1, 10_000 * MS), 100 * MS, 100 * MS)[0] == FROM_FUTURE
    refusal, sent = gate.admit(_cmd(2, 150 * MS), 100 * MS, 100 * MS)  # 50 ms ahead
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
        refusal, sent = gate.admit(_cmd(seq, sent_ms * MS, action), t_recv, now)
        if refusal is None:
            cmd_key = (seq, sent_ms)
            assert last is None or (cmd_key[0] > last[0] and cmd_key[1] > last[1])
            last = cmd_key
            if action != "arm_stop":
                assert now - sent <= AGE
        if gate.last_fresh_ns is not None:
            assert gate.last_fresh_ns <= now  # never a deadline set from the future
