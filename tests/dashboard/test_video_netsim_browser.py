"""The page's video through the link simulator's datagram mode, in headless chromium.

The robot's video server runs with ``link_scenario`` (as ``deepxpalm demo
--scenario`` runs it): each viewer's media crosses a datagram relay under
the scenario, the page's only way to the server. The page's own video.js
reads each presented frame's capture stamp; what it reports (glass to glass,
the FRESH/STALE badge) is what the operator would see.

- metro: the page plays through the simulator, FRESH, every frame having
  crossed it; the comparison with the direct path (p50 within 10 ms of the
  direct one plus the configured delay) is a figure only a quiet machine can
  judge: ``deepxpalm bench --only video_netsim`` gives it a verdict, and this
  test runs that measurement once each way as its smoke check.
- bad_day: the scenario's 2 s outage turns the badge STALE and greys the
  picture, and the page plays again within 2 s of the outage's end (its
  reconnect schedule: docs/dashboard.md).
- metro with a 1 Mbit/s bottleneck towards the page: the encoder's bitrate
  over the last 10 s under 1 Mbit/s (the browser's REMB feedback lowering
  aiortc's VP8 target) and the picture never stops for as long as the page
  itself calls a stream dead (3 s); stalls over 500 ms are the bench's verdict.
"""

from __future__ import annotations

import time

import pytest
from headless_chromium import Chromium, needs_chromium

pytest.importorskip("aiortc", reason="the video needs the 'video' extra")

from common.netsim.scenario import load_scenario
from harness.bench.video_netsim import (
    AGAINST_FRAMES,
    AGAINST_WARMUP,
    RECOVER_S,
    against_direct,
    page_server,
)
from robot_side.camera.stamp import MS_MODULO

#: serial: the video server here runs at the priority of its unit's (Nice=0, below the nodes'
#: -10, as video yields to control on a robot PC), and beside the deployment lane's deployments,
#: whose nodes outrank it, a 2-core machine left it too little to encode: in clean-clone runs
#: the page went STALE mid-session, came back 2.4 s after bad_day's outage, and under the
#: 1 Mbit/s bottleneck showed no frame in 17 s, while each passes on a machine of its own
pytestmark = [pytest.mark.slow, pytest.mark.timeout(150), needs_chromium, pytest.mark.serial]

LIMIT_KBIT = 1000.0
#: the page offers again when no frame is decoded for this long (video.js): a gap this long is
#: the page calling the stream dead
PAGE_DEAD_AFTER_MS = 3000.0


def test_on_metro_the_page_plays_fresh_through_the_simulator_and_the_bench_comparison_runs():
    a = against_direct("metro", sessions=1)
    print(
        f"glass to glass p50: direct {a['direct_p50_ms']} ms, metro {a['through_p50_ms']} ms, "
        f"{a['one_way_ms']} ms configured: {a['off_ms']:+.1f} ms off ({a['idle']:.0%} idle; "
        "the bench's verdict holds it within 10 ms on a quiet machine)"
    )
    assert a["page_errors"] == [], a["page_errors"]
    assert a["through_sent"] > AGAINST_WARMUP + AGAINST_FRAMES, (
        f"the frames did not cross the simulator: {a}"
    )
    assert a["through_fresh"] == ["fresh", "FRESH"], a
    # nothing arrives before the link lets it: the page's median is at least the configured delay
    assert a["through_p50_ms"] >= a["one_way_ms"], a


def _bad_day_with_an_early_outage(tmp_path) -> str:
    """bad_day's link with its 2 s outage at 8 s, not 20: the picture has settled by then,
    and the suite does not wait 12 s more for the same check."""
    from importlib import resources

    text = resources.files("common.netsim.scenarios").joinpath("bad_day.toml").read_text()
    assert "outages = [[20.0, 22.0]]" in text, "bad_day's outage moved: update this test"
    path = tmp_path / "bad_day_early.toml"
    path.write_text(text.replace("outages = [[20.0, 22.0]]", "outages = [[8.0, 10.0]]"))
    return str(path)


def wait_for_frames(browser: Chromium, frames: int, until: float) -> int:
    """Frames the page presented once it has ``frames`` or at ``until`` (monotonic)."""
    n = 0
    while time.monotonic() < until:
        n = browser.evaluate("dxp.video ? dxp.video.latencies.length : 0")
        if n >= frames:
            break
        time.sleep(0.1)
    return n


def test_on_bad_day_the_page_shows_stale_during_the_outage_and_plays_within_2_s_after(tmp_path):
    link = _bad_day_with_an_early_outage(tmp_path)
    scenario = load_scenario(link)
    (t1_s, t2_s), *_ = scenario.to_operator.outages
    # the browser first: the link's clock starts with the video server
    with (
        Chromium(width=1280, height=900) as browser,
        page_server(link) as (server, dashboard),
    ):
        browser.navigate(dashboard.url)
        start = server.link_start_ns / 1e9
        # the outage comes 8 s after the server's start: the page must be playing before it
        played = wait_for_frames(browser, AGAINST_WARMUP, until=start + t1_s - 0.5)
        assert played, (
            f"product: the page showed {played} frames in the {t1_s - 0.5:g} s from the video "
            "server's start to just before the outage"
        )
        wall_minus_mono = time.time() - time.monotonic()
        seen: list[tuple[float, str, bool]] = []  # (s after start, badge, picture greyed)
        back_at = None
        end_ms = round((start + t2_s + wall_minus_mono) * 1000)
        while time.monotonic() < start + t2_s + 6:
            state = browser.evaluate(
                "[dxp.video.freshness.state, dxp.video.lastStamp, "
                "document.getElementById('video').classList.contains('stale'), "
                "document.getElementById('video-fresh-label').textContent]"
            )
            t = time.monotonic() - start
            seen.append((round(t, 2), state[3], state[2]))
            newer = state[1] is not None and (state[1] - end_ms) % MS_MODULO < MS_MODULO // 2
            if t > t2_s and newer and state[0] == "fresh" and back_at is None:
                back_at = t - t2_s
                break
            time.sleep(0.1)
        changes = browser.evaluate("dxp.video.freshnessChanges")
        errors = browser.page_errors()
    assert errors == [], errors
    during = [(t, badge, grey) for t, badge, grey in seen if t1_s + 0.8 < t < t2_s]
    assert during and all(b == "STALE" and grey for _, b, grey in during), (
        f"product: the picture froze in the outage {t1_s}-{t2_s} s but the page said {during}"
    )
    print(f"bad_day: played again {back_at} s after the outage; {changes[-4:]}")
    assert back_at is not None and back_at <= RECOVER_S, (
        f"product: not playing again within {RECOVER_S:g} s of the outage's end: {seen[-10:]}"
    )


def test_under_a_1_mbit_bottleneck_the_picture_keeps_playing_and_the_encoder_settles_under_it():
    from harness.bench.video_netsim import play, with_limit

    limited = with_limit(load_scenario("metro"), LIMIT_KBIT, 40)
    # 17 s: the encoder's rate is read over the last 10 s (7-17 s); measured here it had
    # settled to 354 kbit/s by then (490 over 15-25 s), far under the 1000 of the bottleneck
    row = play(limited, 640, 480, 30.0, seconds=17.0)
    assert row["page_errors"] == [], row["page_errors"]
    gaps = row["longest_gap_after_5s_ms"]
    print(f"1 Mbit/s: encoder {row['encoder_kbit_s']} kbit/s, longest gap {gaps} ms")
    assert row["encoder_kbit_s"] is not None and row["encoder_kbit_s"] < LIMIT_KBIT, (
        f"product: the encoder sent {row['encoder_kbit_s']} kbit/s over the last 10 s "
        f"into a {LIMIT_KBIT:g} kbit/s bottleneck: {row}"
    )
    assert row["frames"] > 0 and gaps is not None and gaps < PAGE_DEAD_AFTER_MS, (
        f"product: the picture stopped for {gaps} ms after 5 s, as long as the page calls a "
        f"stream dead: {row}"
    )
