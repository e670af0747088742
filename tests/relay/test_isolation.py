"""A stalled and a 64 kbit/s subscriber on a relay delay nobody else (libzmq issue 3280).

Side by side in one run: the same stream goes to two relays; relay A also
serves a subscriber that never reads and one that reads at 8,000 bytes/s,
relay B does not. The normal subscribers of both are read by one loop in one
process, in alternating order, so the only difference is the relay's company.
"""

from __future__ import annotations

import pytest

from harness.bench.relay import run_isolation

pytestmark = [pytest.mark.slow]


def _check(r: dict) -> float:
    c = r["clients"]
    sent = r["sent"]
    # every message, stimulus and frame, reached every normal subscriber on both relays
    for label in ("a1", "a2", "b1", "b2", "b3", "b4"):
        assert c[label]["stimuli"] == sent, (label, c[label])
    # the stalled one got nothing and the slow one a trickle: the relay dropped for them
    assert c["stall"]["received"] == 0
    assert 0 < c["slow"]["bytes"] < 1.5 * r["slow_bytes_per_s"] * r["duration_s"]
    assert c["slow"]["stimuli"] < 0.2 * sent
    return r["p99_ratio"]


def test_a_stalled_and_a_slow_subscriber_move_no_other_subscribers_p99(tmp_path, quiet_gc):
    """A second trial, with the relay processes' roles swapped, when the first exceeds the
    goal: on a shared 2-core machine one relay process can be descheduled for a few ms in a
    run, which moves a p99; a real isolation failure (libzmq issue 3280's) fails both.
    """
    trials = []
    for swap in (False, True):
        r = run_isolation(duration_s=8.0, rate_hz=250.0, workdir=tmp_path / str(swap), swap=swap)
        trials.append(_check(r))
        print(
            "p99 with / without the stalled and slow subscribers:",
            round(trials[-1], 3),
            r["pooled"],
        )
        if trials[-1] <= 1.10:
            break
    assert min(trials) <= 1.10, trials
