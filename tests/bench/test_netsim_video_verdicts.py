"""The link simulator's and the video's bench figures: each row a verdict, computed, never typed."""

from __future__ import annotations

import pytest

from harness.bench import netsim, video, video_netsim


def _datagram_row(**kw) -> dict:
    row = {
        "scenario": "fixed_20ms",
        "sent": 400,
        "received": 400,
        "direct_p50_ms": 0.02,
        "configured_p50_ms": 20.0,
        "floor_ms": 20.0,
        "via_min_ms": 20.01,
        "via_p50_ms": 20.05,
        "extra_p50_ms": 0.03,
        "early": 0,
        "ok": True,
    }
    return {**row, **kw}


def test_every_datagram_row_is_a_verdict_and_an_early_one_fails():
    section = {
        "runs": [],
        "datagram_runs": [_datagram_row(), _datagram_row(scenario="metro", early=3, ok=False)],
    }
    got = netsim.verdicts({"sections": {"netsim": section}})
    assert [v.passed for v in got] == [True, False]
    assert "3 early" in got[1].measured
    assert netsim.verdicts({"sections": {"netsim": {"error": "x"}}}) == []


@pytest.mark.slow
@pytest.mark.untimed  # its one bound (none early) holds whatever the load
def test_a_datagram_run_measures_and_judges_its_rows():
    row = netsim.datagram_run("fixed_20ms", 0.2)
    assert row["received"] == row["sent"] == 40
    assert row["early"] == 0 and row["via_min_ms"] >= 20.0


def _viewers(**kw) -> dict:
    m = {
        "viewers": 4,
        "seconds": 60.0,
        "p50_ms": 45.0,
        "p99_ms": 70.0,
        "stalls_over_500ms": 0,
        "longest_gap_ms": 80.0,
        "fps_per_viewer": 29.0,
        "fps_per_viewer_max": 29.5,
        "fps_source": 30.0,
        "ended_early": 0,
        "machine_idle_cpu": 0.3,
    }
    return {**m, **kw}


def test_four_viewers_pass_only_served_fresh_and_alike():
    assert video.many_viewers_verdict(_viewers()).passed
    assert not video.many_viewers_verdict(_viewers(p50_ms=120.0)).passed
    assert not video.many_viewers_verdict(_viewers(ended_early=1)).passed
    assert not video.many_viewers_verdict(_viewers(fps_per_viewer=20.0)).passed  # not alike
    assert not video.many_viewers_verdict(_viewers(stalls_over_500ms=1)).passed


def test_metro_is_judged_against_direct_sessions_of_the_same_run():
    def results(off_ms: float | None, errors: tuple[str, ...] = ()) -> dict:
        section: dict = {"rows": []}
        if off_ms is not None:
            section["against_direct"] = {
                "through_p50_ms": 40.0 + 4.0 + off_ms,
                "direct_p50_ms": 40.0,
                "one_way_ms": 4.0,
                "off_ms": off_ms,
                "direct_spread_ms": 0.5,
                "page_errors": list(errors),
            }
        return {"sections": {"video_netsim": section}}

    (ok,) = video_netsim.verdicts(results(3.0))
    assert ok.passed and "+3.0 ms" in ok.measured
    assert not video_netsim.verdicts(results(-12.0))[0].passed  # the delay did not show
    assert not video_netsim.verdicts(results(15.0))[0].passed  # the simulator added its own
    assert not video_netsim.verdicts(results(1.0, ("TypeError",)))[0].passed
    assert video_netsim.verdicts(results(None))[0].passed is None  # not measured
