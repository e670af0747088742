"""The fidelity rig runs, and what it sees holds on any machine.

The rig of ``harness.bench.netsim_fidelity``: a PUB sends 100 small messages a
second carrying their send time, to a SUB directly and to another through
``deepxpalm netsim`` (its own process, byte-stream mode), on loopback. How
close the simulator keeps to its scenario (p50 within 0.15 ms of a direct
link at zero delay, p5/p50/p95 within 0.5 ms or 5 % with a delay) only a
quiet machine can judge: ``deepxpalm bench --only netsim`` runs the rig 20 s
a scenario and gives each row a verdict. Here, for 2 s: every message
arrives, none before the scenario's floor, none later than the operator's
staleness limit beyond what the scenario configures.
"""

from __future__ import annotations

import pytest

from common.netsim.scenario import load_scenario
from harness.bench.netsim_fidelity import measure
from operator_side.node.config import OperatorLinkConfig

pytestmark = pytest.mark.slow

SECONDS = 2.0
#: Beyond its configured delay, the most a message may be late on any machine: later than
#: this, the operator would show a stale link the scenario does not have.
LATE_MS = OperatorLinkConfig().stale_after_ms


def test_through_netsim_nothing_arrives_before_the_floor_or_later_than_the_staleness_limit():
    run = measure("intercontinental", seconds=SECONDS)
    config = load_scenario("intercontinental").to_operator
    floor, p50 = config.delay_quantile_ms(0.0), config.delay_quantile_ms(0.5)
    assert len(run.via_ms) >= 0.99 * SECONDS * run.rate_hz, run.as_dict()
    assert len(run.direct_ms) >= 0.99 * SECONDS * run.rate_hz, run.as_dict()
    assert min(run.via_ms) >= floor, f"{min(run.via_ms):.3f} ms, under the {floor} ms floor"
    measured = run.quantiles(run.via_ms)[0.5]
    assert measured < p50 + LATE_MS, f"p50 {measured:.2f} ms, configured {p50:.2f} ms"
