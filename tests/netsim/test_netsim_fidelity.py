"""Seen from outside, the simulator adds what its scenario says and little else.

The rig of ``common.netsim.fidelity``: a PUB sends 100 small messages a
second carrying their send time, to a SUB directly and to another through
``deepxpalm netsim`` (its own process, byte-stream mode), on loopback, for
6 s (600 messages a path: the p99 rests on six of them, enough for a
0.5 ms bound; the bench runs 20 s). On a shared 2-core machine another job
can stall any process for milliseconds, so a failed run is measured once
more, and the tails are only judged when the machine is not overloaded
(see ``assert_faithful`` in conftest.py).
"""

from __future__ import annotations

import pytest

from common.netsim.fidelity import measure

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("quiet_gc")]

SECONDS = 6.0


def test_at_zero_delay_the_relay_is_about_as_fast_as_a_direct_link(assert_faithful):
    assert_faithful(measure("none", seconds=SECONDS), lambda: measure("none", seconds=SECONDS))


# metro is intercontinental's shape at a smaller delay: the bench's table holds both
@pytest.mark.parametrize("scenario", ["intercontinental"])
def test_a_delayed_scenario_adds_its_configured_distribution(scenario, assert_faithful):
    assert_faithful(measure(scenario, seconds=SECONDS), lambda: measure(scenario, seconds=SECONDS))
