"""The replay window commands and signed telemetry share: once, in order, reordering bounded."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from common.wire.replay_window import ReplayWindow

pytestmark = [pytest.mark.slow, pytest.mark.untimed]  # no timing checked


def _offer(w: ReplayWindow, session: int, stream: bytes, seq: int, t: int) -> bool:
    """What a receiver does: accepted (and recorded) unless the window calls it a replay."""
    if w.replayed(session, stream, seq, t):
        return False
    w.accept(session, stream, seq, t)
    return True


arrivals = st.lists(
    st.tuples(st.integers(0, 3), st.sampled_from([b"STIM", b"HBRT"]), st.integers(0, 200)),
    max_size=120,
)


@settings(max_examples=300, deadline=None)
@given(width=st.integers(0, 70), events=arrivals)
def test_nothing_is_accepted_twice_whatever_arrives(width, events):
    w = ReplayWindow(width=width)
    accepted: set[tuple[int, bytes, int]] = set()
    for session, stream, seq in events:
        if _offer(w, session, stream, seq, seq * 1000):  # an honest clock: time rises with seq
            assert (session, stream, seq) not in accepted
            accepted.add((session, stream, seq))
    for key in accepted:  # and a replay of any of them later still is refused
        assert w.replayed(*key, key[2] * 1000)


@settings(max_examples=300, deadline=None)
@given(
    width=st.integers(1, 70),
    seqs=st.lists(st.integers(0, 300), unique=True, max_size=100),
)
def test_an_honest_stream_reordered_is_accepted_exactly_within_the_window(width, seqs):
    """Distinct messages arriving in any order: one is refused only if it lags the newest by
    ``width`` or more (the documented limit of reordering)."""
    w = ReplayWindow(width=width)
    highest = None
    for seq in seqs:
        expected = highest is None or seq > highest or highest - seq < width
        assert _offer(w, 1, b"HBRT", seq, seq * 1000) == expected, (seq, highest)
        highest = seq if highest is None else max(highest, seq)


@settings(max_examples=300, deadline=None)
@given(events=st.lists(st.tuples(st.integers(0, 20), st.integers(0, 20)), max_size=60))
def test_without_width_seq_and_send_time_both_strictly_increase(events):
    """Width 0 is the command rule: a reordered, repeated or back-dated message is refused."""
    w = ReplayWindow(width=0)
    last = None
    for seq, t in events:
        if _offer(w, 7, b"CMND", seq, t):
            assert last is None or (seq > last[0] and t > last[1])
            last = (seq, t)


@settings(max_examples=200, deadline=None)
@given(
    width=st.integers(0, 70),
    a=st.lists(st.integers(0, 100), max_size=40),
    b=st.lists(st.integers(0, 100), max_size=40),
    order=st.lists(st.booleans(), max_size=80),
)
def test_sessions_do_not_disturb_each_other(width, a, b, order):
    """Two sessions interleaved decide exactly as each alone: a restart does not move the old
    window, and the old run's messages do not move the new one's."""
    alone = {}
    for name, seqs in (("a", a), ("b", b)):
        w = ReplayWindow(width=width)
        alone[name] = [_offer(w, 1, b"STIM", s, s) for s in seqs]
    w = ReplayWindow(width=width)
    got = {"a": [], "b": []}
    queues = {"a": list(a), "b": list(b)}
    picks = iter(order)
    while queues["a"] or queues["b"]:
        name = "a" if not queues["b"] or (queues["a"] and next(picks, True)) else "b"
        s = queues[name].pop(0)
        got[name].append(_offer(w, 1 if name == "a" else 2, b"STIM", s, s))
    assert got == alone


def test_a_forgotten_session_is_the_oldest_heard():
    w = ReplayWindow(width=4, max_sessions=2)
    for session in (1, 2):
        w.accept(session, b"STIM", 5, 5)
    w.accept(1, b"STIM", 6, 6)  # session 1 heard again: session 2 is now the oldest
    w.accept(3, b"STIM", 1, 1)
    assert 1 in w and 3 in w and 2 not in w


def test_a_window_needs_sane_bounds():
    with pytest.raises(ValueError):
        ReplayWindow(width=-1)
    with pytest.raises(ValueError):
        ReplayWindow(max_sessions=0)
