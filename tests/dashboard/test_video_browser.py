"""Video from the robot's video server to the dashboard in headless chromium, measured.

A short run of the benchmark's glass-to-glass measurement (``deepxpalm
bench`` runs it over 1,000 frames): the stamped test pattern crosses real
WebRTC on loopback, the page reads each frame's capture time from its
pixels, and the source is closed once the tab is gone.
"""

from __future__ import annotations

import pytest
from headless_chromium import MISSED_STAMPS_ALLOWED, needs_chromium

pytest.importorskip("aiortc")

from harness.bench.video import glass_to_glass

pytestmark = [
    pytest.mark.slow,
    pytest.mark.timeout(90),
    needs_chromium,
]


def test_glass_to_glass_latency_in_the_browser():
    out = glass_to_glass(frames=150)
    assert out["page_errors"] == []
    assert out["frames"] >= 150, out
    assert out["unreadable_frames"] <= MISSED_STAMPS_ALLOWED, (
        f"{out['unreadable_frames']} stamps unreadable, at {out['unreadable_at']}: {out}"
    )
    # Loose bounds: this machine is shared (a load of 12 on 2 cores has been seen, with
    # second-long stalls in every process); deepxpalm bench reports the real figures.
    assert 0 < out["latency_ms"]["min"] < 200, out  # a stamp from the future would be a bug
    assert out["latency_ms"]["p50"] < 400, out
    assert out["fps_presented"] > 5, out
    assert out["source_opened"] == 1
