"""The fidelity tests' judgement: scaled to this machine's hop, never blind to the simulator."""

from __future__ import annotations

from harness.bench.netsim_fidelity import FidelityRun

N = 1000


def _run(direct_ms: float, via_extra_ms: float, configured_ms: float = 18.0) -> FidelityRun:
    """A run whose paths cost a constant: the direct hop, and configured + hop + extra."""
    return FidelityRun(
        "walk",
        "stream",
        10.0,
        100.0,
        direct_ms=[direct_ms] * N,
        via_ms=[configured_ms + direct_ms + via_extra_ms] * N,
        configured={q: configured_ms for q in (0.05, 0.5, 0.95, 0.99)},
    )


def test_on_a_machine_with_a_usual_hop_the_bench_tolerance_holds():
    assert all(_run(0.15, 0.8).scaled_verdicts().values())  # 5 % of 18.15 ms is 0.91
    assert not any(_run(0.15, 1.5).scaled_verdicts().values())


def test_a_slow_hop_widens_the_tolerance_by_its_excess_only():
    # the quiet clean-clone run that failed: direct 0.93 ms, the relay path 1.47 ms above
    assert all(_run(0.93, 1.47).scaled_verdicts().values())
    # a simulator that adds milliseconds of its own still fails on that machine
    assert not any(_run(0.93, 3.0).scaled_verdicts().values())


def test_a_zero_delay_run_may_cost_one_more_direct_hop():
    assert all(_run(0.3, 0.3, configured_ms=0.0).scaled_verdicts().values())
    assert not _run(0.3, 0.7, configured_ms=0.0).scaled_verdicts()["p50"]
