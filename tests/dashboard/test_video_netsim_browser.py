"""The page's video through the link simulator's datagram mode, in headless chromium.

The robot's video server runs with ``link_scenario`` (as ``deepxpalm demo
--scenario`` runs it): each viewer's media crosses a datagram relay under
the scenario, the page's only way to the server. The page's own video.js
reads each presented frame's capture stamp; what it reports (glass to glass,
the FRESH/STALE badge) is what the operator would see.

- metro: glass to glass p50 within 10 ms of the configured one-way delay
  plus the direct figure, measured in the same test on the same page code.
- bad_day: the scenario's 2 s outage (20 s after the video server starts)
  turns the badge STALE and greys the picture, and the page plays again
  within 2 s of the outage's end.
- metro with a 1 Mbit/s bottleneck towards the page: no gap over 1 s after
  the first 5 s, and the encoder's bitrate over the last 10 s under 1 Mbit/s
  (the browser's REMB feedback lowering aiortc's VP8 target).
"""

from __future__ import annotations

import contextlib
import statistics
import time
from collections.abc import Iterator

import pytest
from headless_chromium import Chromium, needs_chromium

pytest.importorskip("aiortc", reason="the video needs the 'video' extra")

from common.netsim.scenario import load_scenario
from deploy.bench.video import cpu_times, idle_share
from robot_side.video.stamp import MS_MODULO

pytestmark = [pytest.mark.slow, pytest.mark.timeout(150), needs_chromium]

WARMUP = 15  # frames: ICE, the first keyframe, the jitter buffer settling
FRAMES = 45
SPARE_IDLE = 0.15  # under this share of idle CPU, the machine sets the pace, not the product
LIMIT_KBIT = 1000.0
#: not a divisor of the page's 60 Hz paint: at 15 fps each frame met the paint at the same
#: phase for a whole session, so a session's p50 carried a fixed 0-17 ms of its own (measured:
#: direct sessions 22-31 ms at 15 fps, 30.5-33 ms at 14 fps); at 14 fps every session
#: samples every phase
FPS = 14


@contextlib.contextmanager
def _page_server(scenario: str) -> Iterator[tuple]:
    """A video server whose media crosses ``scenario`` ("" = direct) and a dashboard on it."""
    from operator_side.config import OperatorConfig
    from operator_side.dashboard import Dashboard, DashboardConfig
    from operator_side.node import OperatorNode
    from operator_side.servos.recording import RecordingServoBus
    from robot_side.camera.config import TestPatternConfig
    from robot_side.camera.test_pattern import TestPatternCamera
    from robot_side.video.server import VideoConfig, VideoServer

    source = TestPatternCamera(TestPatternConfig(width=320, height=240, fps=FPS))
    node = OperatorNode(OperatorConfig(), RecordingServoBus())  # the page needs a node; idle
    with VideoServer(source, VideoConfig(port=0, link_scenario=scenario)) as server:
        dashboard = Dashboard(node, DashboardConfig(port=0, video_url=server.url))
        dashboard.start()
        try:
            yield server, dashboard
        finally:
            dashboard.stop()


def _latencies_after_warmup(browser: Chromium, url: str) -> list[float]:
    browser.navigate(url)
    browser.wait_until(
        "dxp.video ? dxp.video.latencies.length : 0",
        lambda n: n >= WARMUP + FRAMES,
        timeout_s=60,
        poll_s=0.5,
    )
    return browser.evaluate("dxp.video.latencies")[WARMUP:]


def test_on_metro_the_page_plays_at_the_direct_latency_plus_the_configured_delay():
    one_way = load_scenario("metro").to_operator.delay_quantile_ms(0.5)
    cpu0 = cpu_times()
    direct: list[list[float]] = []
    through: list[list[float]] = []
    with Chromium(width=1280, height=900) as browser:
        # direct and metro taken in turns, twice each: one page session's p50 may still wander
        # by a few ms from the next (the receiver's jitter buffer), so the direct figure is
        # two sessions and its spread is known
        for _ in range(2):
            with _page_server("") as (_, dashboard):
                direct.append(_latencies_after_warmup(browser, dashboard.url))
            with _page_server("metro") as (server, dashboard):
                through.append(_latencies_after_warmup(browser, dashboard.url))
                fresh = browser.evaluate("dxp.video.freshness")
                counters = [p.counters() for p in server.media_paths]
                badge = browser.evaluate("document.getElementById('video-fresh-label').textContent")
        errors = browser.page_errors()
    idle = idle_share(cpu0, cpu_times())
    assert errors == [], errors
    sent = sum(c["to_operator"]["sent"] for path in counters for c in path.values())
    assert sent > WARMUP + FRAMES, f"the frames did not cross the simulator: {counters}"
    assert fresh["state"] == "fresh" and badge == "FRESH", (fresh, badge)
    d_p50 = statistics.median([x for run in direct for x in run])
    m_p50 = statistics.median([x for run in through for x in run])
    d_spread = abs(statistics.median(direct[0]) - statistics.median(direct[1]))
    off = m_p50 - (d_p50 + one_way)
    print(
        f"glass to glass p50: direct {d_p50:.1f} ms (sessions {d_spread:.1f} ms apart), "
        f"metro {m_p50:.1f} ms ({idle:.0%} idle)"
    )
    if abs(off) > 10.0 and (idle < SPARE_IDLE or d_spread > 10.0):
        pytest.skip(
            f"not checkable here: {off:+.1f} ms off with {idle:.0%} of the CPU idle and the "
            f"direct sessions {d_spread:.1f} ms apart"
        )
    assert abs(off) <= 10.0, (
        f"product: through metro p50 {m_p50:.1f} ms, direct {d_p50:.1f} ms + {one_way} ms "
        f"configured: {off:+.1f} ms off ({idle:.0%} idle, direct sessions {d_spread:.1f} ms "
        "apart)"
    )


def _bad_day_with_an_early_outage(tmp_path) -> str:
    """bad_day's link with its 2 s outage at 8 s, not 20: the picture has settled by then,
    and the suite does not wait 12 s more for the same check."""
    from importlib import resources

    text = resources.files("common.netsim.scenarios").joinpath("bad_day.toml").read_text()
    assert "outages = [[20.0, 22.0]]" in text, "bad_day's outage moved: update this test"
    path = tmp_path / "bad_day_early.toml"
    path.write_text(text.replace("outages = [[20.0, 22.0]]", "outages = [[8.0, 10.0]]"))
    return str(path)


def test_on_bad_day_the_page_shows_stale_during_the_outage_and_plays_within_2_s_after(tmp_path):
    link = _bad_day_with_an_early_outage(tmp_path)
    scenario = load_scenario(link)
    (t1_s, t2_s), *_ = scenario.to_operator.outages
    with (
        _page_server(link) as (server, dashboard),
        Chromium(width=1280, height=900) as browser,
    ):
        browser.navigate(dashboard.url)
        browser.wait_until(
            "dxp.video ? dxp.video.latencies.length : 0", lambda n: n >= WARMUP, timeout_s=60
        )
        start = server.link_start_ns / 1e9
        wall_minus_mono = time.time() - time.monotonic()
        if time.monotonic() > start + t1_s - 2:
            pytest.skip(f"load: the page played only {time.monotonic() - start:.0f} s in")
        cpu0 = cpu_times()
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
        idle = idle_share(cpu0, cpu_times())
        changes = browser.evaluate("dxp.video.freshnessChanges")
        errors = browser.page_errors()
    assert errors == [], errors
    during = [(t, badge, grey) for t, badge, grey in seen if t1_s + 0.8 < t < t2_s]
    assert during and all(b == "STALE" and grey for _, b, grey in during), (
        f"product: the picture froze in the outage {t1_s}-{t2_s} s but the page said {during}"
    )
    print(f"bad_day: played again {back_at} s after the outage, {idle:.0%} idle; {changes[-4:]}")
    if (back_at is None or back_at > 2.0) and idle < SPARE_IDLE:
        pytest.skip(f"load, not product: played again after {back_at} s, {idle:.0%} idle")
    assert back_at is not None and back_at <= 2.0, (
        f"product: not playing again within 2 s of the outage's end: {seen[-10:]}"
    )


def test_under_a_1_mbit_bottleneck_the_picture_keeps_playing_and_the_encoder_settles_under_it():
    from deploy.bench.video_netsim import play, with_limit

    limited = with_limit(load_scenario("metro"), LIMIT_KBIT, 40)
    cpu0 = cpu_times()
    # 17 s: the encoder's rate is read over the last 10 s (7-17 s); measured here it had
    # settled to 354 kbit/s by then (490 over 15-25 s), far under the 1000 of the bottleneck
    row = play(limited, 640, 480, 30.0, seconds=17.0)
    idle = idle_share(cpu0, cpu_times())
    assert row["page_errors"] == [], row["page_errors"]
    gaps = row["longest_gap_after_5s_ms"]
    print(
        f"1 Mbit/s: encoder {row['encoder_kbit_s']} kbit/s, longest gap {gaps} ms, {idle:.0%} idle"
    )
    assert row["encoder_kbit_s"] is not None and row["encoder_kbit_s"] < LIMIT_KBIT, (
        f"product: the encoder sent {row['encoder_kbit_s']} kbit/s over the last 10 s "
        f"into a {LIMIT_KBIT:g} kbit/s bottleneck: {row}"
    )
    if gaps > 1000 and idle < SPARE_IDLE:
        pytest.skip(f"load, not product: a {gaps:.0f} ms gap with {idle:.0%} of the CPU idle")
    assert gaps <= 1000, f"product: the picture stopped for {gaps:.0f} ms after 5 s: {row}"
