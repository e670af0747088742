"""A stalled and a 64 kbit/s subscriber on a relay delay nobody else (libzmq issue 3280).

Side by side in one run: the same stream goes to two relays; relay A also
serves a subscriber that never reads and one that reads at 8,000 bytes/s,
relay B does not. The normal subscribers of both are read by one loop in one
process, in alternating order, so the only difference is the relay's company.
"""

from __future__ import annotations

import pytest

from harness.bench.relay import ISOLATION_GOAL, run_isolation

pytestmark = [pytest.mark.slow]

#: what one stall of a busy machine adds to one relay process's p99 and not the other's
STALL_MS = 50.0


def _check(r: dict) -> tuple[float, float]:
    c = r["clients"]
    sent = r["sent"]
    lost = {label: sent - c[label]["stimuli"] for label in ("a1", "a2", "b1", "b2", "b3", "b4")}
    # every stimulus reached every normal subscriber on relay A, as on relay B. A relay drops
    # only for a connection that has not taken its messages for a while (its queue of 100,
    # 0.2 s of this stream, and the socket buffers); the one process that reads all of them,
    # starved that long on a loaded machine, then loses as much on B as on A
    worst_b = max(lost[x] for x in ("b1", "b2", "b3", "b4"))
    allowed = 0 if worst_b == 0 else int(1.5 * worst_b) + 10
    for label in ("a1", "a2"):
        assert lost[label] <= allowed, (
            f"{label} lost {lost[label]} of {sent} stimuli beside the stalled and slow "
            f"subscribers; B's, without them, lost {worst_b} at most: {lost}"
        )
    if worst_b:
        print(f"the reading process fell behind the relays' queues on both relays: lost {lost}")
    # the stalled one got nothing and the slow one a trickle: the relay dropped for them
    assert c["stall"]["received"] == 0
    assert 0 < c["slow"]["bytes"] < 1.5 * r["slow_bytes_per_s"] * r["duration_s"]
    assert c["slow"]["stimuli"] < 0.2 * sent
    return r["pooled"]["with_stalled"]["p99_us"] / 1e3, r["pooled"]["without"]["p99_us"] / 1e3


def test_a_stalled_and_a_slow_subscriber_move_no_other_subscribers_p99(tmp_path, quiet_gc):
    """A's p99 within the bench's goal of B's, plus what a busy machine's stall adds to one p99.

    ``deepxpalm bench --only relay`` judges the ratio alone (ISOLATION_GOAL, 10 %) on a quiet
    machine. Here the run shares the machine with the paired lane's deployments, whose
    stalls put one relay process's p99 at 19 ms against the other's 16 ms, or 154 ms against
    104 ms, in one run: a ratio a machine moves. An isolation failure (libzmq issue 3280's:
    a relay that waits for its slowest subscriber) paces A's subscribers to the 64 kbit/s
    one and falls seconds behind. A second trial, the relay processes' roles swapped, runs
    when the first exceeds the bound.
    """
    trials = []
    for swap in (False, True):
        r = run_isolation(duration_s=8.0, rate_hz=250.0, workdir=tmp_path / str(swap), swap=swap)
        with_ms, without_ms = _check(r)
        bound_ms = ISOLATION_GOAL * without_ms + STALL_MS
        trials.append((round(with_ms, 1), round(without_ms, 1), round(bound_ms, 1)))
        print(f"p99 with / without the stalled and slow subscribers: {trials[-1][:2]} ms")
        if with_ms <= bound_ms:
            return
    raise AssertionError(
        "p99 of the subscribers beside the stalled and slow ones, without them, and the bound "
        f"(10 % more plus {STALL_MS:.0f} ms), in ms, each trial: {trials}"
    )
