"""Trace replay: a recorded link comes out of the simulator as it was recorded."""

from __future__ import annotations

import random

import pytest

from common.errors import ConfigError
from common.netsim.impairments import NS_PER_MS, DirectionImpairment
from common.netsim.scenario import load_scenario, scenario_from_dict
from common.netsim.trace import delay_percentiles_ms, load_delay_trace
from common.netsim.virtual import VirtualLink
from harness.bench.netsim_fidelity import measure
from operator_side.node.config import OperatorLinkConfig

pytestmark = pytest.mark.usefixtures("quiet_gc")

QUANTILES = (0.05, 0.5, 0.95)


def _delivered_ms(scenario, seconds: float, rate_hz: float) -> list[float]:
    link = VirtualLink(scenario, seed=2)
    period = round(1e9 / rate_hz)
    sent = {}
    for i in range(round(seconds * rate_hz)):
        t = i * period
        link.send("to_operator", t, i.to_bytes(4, "little"))
        sent[i] = t
    out = link.deliver_until(10**15)
    return sorted((due - sent[int.from_bytes(data, "little")]) / NS_PER_MS for due, _, data in out)


def _nearest_rank(values: list[float], q: float) -> float:
    return values[round(q * (len(values) - 1))]


def test_the_shipped_trace_replays_with_its_recorded_percentiles():
    scenario = load_scenario("loopback_trace")
    trace = load_delay_trace(scenario.to_operator.trace_file)
    recorded = delay_percentiles_ms(trace, QUANTILES)
    # two loops of the 30-s recording, at twice its probe rate
    delivered = _delivered_ms(scenario, 60.0, 100.0)
    for q in QUANTILES:
        got = _nearest_rank(delivered, q)
        assert got == pytest.approx(recorded[q], rel=0.05), f"p{q * 100:g}"


def test_a_delay_trace_is_followed_in_time_and_loops(tmp_path):
    path = tmp_path / "steps.delays"
    path.write_text("# t_s delay_ms\n0.0 5\n1.0 20\n2.0 10\n")
    engine = DirectionImpairment(
        scenario_from_dict({"both": {"trace_file": str(path), "delay_ms": 1.0}}).to_operator,
        start_ns=0,
    )
    at = {
        t: engine.process(round(t * 1e9), b"x")[0][0] / 1e6 - t * 1e3 for t in (0.5, 1.5, 2.5, 3.5)
    }
    # each sample holds until the next; the 3-s recording then starts again
    assert at == pytest.approx({0.5: 6.0, 1.5: 21.0, 2.5: 11.0, 3.5: 6.0})


def test_a_mahimahi_trace_delivers_at_its_opportunities(tmp_path):
    path = tmp_path / "link.mahi"
    path.write_text("\n".join(str(ms) for ms in (2, 4, 6, 8, 10)) + "\n")
    config = scenario_from_dict(
        {"both": {"trace_file": str(path), "trace_format": "mahimahi"}}
    ).to_operator
    engine = DirectionImpairment(config, start_ns=0)
    ms = NS_PER_MS
    assert engine.process(0, bytes(100))[0][0] == 2 * ms  # the first opportunity
    assert engine.process(0, bytes(100))[0][0] == 4 * ms  # queued behind it
    assert engine.process(0, bytes(3000))[0][0] == 8 * ms  # two packets: two opportunities
    assert engine.process(9 * ms, bytes(10))[0][0] == 10 * ms
    assert engine.process(11 * ms, bytes(10))[0][0] == 12 * ms  # looped: 10 + 2


def test_a_bad_trace_is_refused_with_its_line(tmp_path):
    path = tmp_path / "bad.delays"
    path.write_text("0.0 1.0\n0.5 oops\n")
    with pytest.raises(ConfigError, match="sample 2"):
        load_delay_trace(path)


@pytest.mark.slow
def test_a_trace_scenario_through_the_relay_stays_inside_its_recorded_range(tmp_path):
    """Over real sockets via ``deepxpalm netsim``: no message faster than the trace allows.

    A random walk between 5 and 25 ms stands in for a recorded wide-area
    path (the shipped loopback recording is below the relay's own cost). Its
    percentiles through the relay against the trace's are the bench's figure
    (``deepxpalm bench --only netsim``, the loopback_trace row); here every
    message arrives, none under the walk's 5 ms floor, none later than the
    operator's staleness limit beyond its 25 ms ceiling.
    """
    rng = random.Random(7)
    d, lines = 12.0, []
    for i in range(500):  # 10 s at 50 samples a second
        d = min(25.0, max(5.0, d + rng.gauss(0.0, 1.0)))
        lines.append(f"{i * 0.02:.2f} {d:.3f}")
    (tmp_path / "walk.delays").write_text("\n".join(lines) + "\n")
    (tmp_path / "walk.toml").write_text(
        'description = "a random walk"\n[both]\ntrace_file = "walk.delays"\n'
    )
    run = measure(str(tmp_path / "walk.toml"), seconds=2.0)
    assert len(run.via_ms) >= 0.99 * 2.0 * run.rate_hz, run.as_dict()
    floor = min(float(line.split()[1]) for line in lines)
    ceiling = max(float(line.split()[1]) for line in lines)
    assert min(run.via_ms) >= floor, f"{min(run.via_ms):.3f} ms, under the trace's {floor} ms"
    late = OperatorLinkConfig().stale_after_ms
    assert max(run.via_ms) < ceiling + late, f"{max(run.via_ms):.1f} ms, trace at most {ceiling}"
