"""The page's input decoding, run in headless chromium on raw device input.

SpaceMouse reports are byte strings laid out as 3Dconnexion devices send
them (report ids 1, 2, 3; int16 little-endian); gamepad states are what the
Gamepad API hands the page. The functions under test are the ones the
dashboard runs (``jog.js``), evaluated in the browser, not a Python copy.
"""

from __future__ import annotations

import itertools
import json
import random
import struct

import pytest
from headless_chromium import Chromium, needs_chromium
from test_dashboard_server import FakeNode

from common.config.typed import to_dict
from operator_side.dashboard import Dashboard, DashboardConfig
from operator_side.dashboard.jog_config import JogConfig

pytestmark = [
    pytest.mark.slow,
    pytest.mark.timeout(60),
    needs_chromium,
]

CFG = to_dict(JogConfig())


@pytest.fixture(scope="module")
def browser():
    d = Dashboard(FakeNode(), DashboardConfig(port=0))
    d.start()
    try:
        with Chromium() as b:
            b.navigate(d.url)
            b.wait_for("typeof JOG === 'object' && dxp.jog !== null", 10)
            yield b
    finally:
        d.stop()


def js(browser: Chromium, expr: str):
    return browser.evaluate(f"(() => {{ const CFG = {json.dumps(CFG)}; return {expr}; }})()")


def report(*values: int, fmt: str = "<3h") -> str:
    return f"new Uint8Array({json.dumps(list(struct.pack(fmt, *values)))})"


def test_older_spacemouse_separate_translation_rotation_and_button_reports(browser):
    state = js(
        browser,
        "(() => { let s = JOG.decodeSpaceMouse(1, " + report(120, -350, 7) + ", null);"
        "s = JOG.decodeSpaceMouse(2, " + report(-5, 0, 349) + ", s);"
        "s = JOG.decodeSpaceMouse(3, " + report(0b10, fmt="<B") + ", s);"
        "return s; })()",
    )
    assert state == {"t": [120, -350, 7], "r": [-5, 0, 349], "buttons": 2}


def test_newer_spacemouse_combined_report_and_two_byte_buttons(browser):
    state = js(
        browser,
        "(() => { let s = JOG.decodeSpaceMouse(1, "
        + report(-1, 2, -3, 4, -5, 6, fmt="<6h")
        + ", null); return JOG.decodeSpaceMouse(3, "
        + report(0x0101, fmt="<H")
        + ", s); })()",
    )
    assert state == {"t": [-1, 2, -3], "r": [4, -5, 6], "buttons": 0x0101}


def test_spacemouse_mapping_enable_and_dead_zone(browser):
    # cap pushed away and twisted, left button held
    held = js(
        browser,
        "JOG.spaceMouseTwist({t: [0, -350, 0], r: [0, 0, 175], buttons: 1}, CFG.spacemouse)",
    )
    assert held["enabled"] is True
    vx, vy, vz, wx, wy, wz = held["twist"]
    assert vx == pytest.approx(1.0) and vy == 0 and vz == 0 and wx == 0 and wy == 0
    dz, n = CFG["spacemouse"]["dead_zone"], CFG["spacemouse"]["curve_exponent"]
    assert wz == pytest.approx(-(((0.5 - dz) / (1 - dz)) ** n))
    released = js(
        browser, "JOG.spaceMouseTwist({t: [0, -350, 0], r: [0, 0, 0], buttons: 2}, CFG.spacemouse)"
    )
    assert released == {"enabled": False, "twist": [0, 0, 0, 0, 0, 0]}
    resting = js(
        browser, "JOG.spaceMouseTwist({t: [20, -25, 10], r: [0, 0, 0], buttons: 1}, CFG.spacemouse)"
    )
    assert resting["twist"] == [0, 0, 0, 0, 0, 0]  # inside the dead zone (cap at rest)


def test_gamepad_mapping_triggers_enable_and_a_drifting_stick(browser):
    pad = {
        "axes": [0.05, -0.8, 0.0, 0.0],  # left stick: slight drift in x, mostly forward
        "buttons": [{"pressed": False, "value": 0}] * 5
        + [{"pressed": True, "value": 1}]  # 5: enable (right bumper)
        + [{"pressed": False, "value": 0.2}, {"pressed": True, "value": 0.9}],  # triggers
    }
    out = js(browser, f"JOG.gamepadTwist({json.dumps(pad)}, CFG.gamepad)")
    dz, n = CFG["gamepad"]["dead_zone"], CFG["gamepad"]["curve_exponent"]
    shape = lambda x: (1 if x > 0 else -1) * ((abs(x) - dz) / (1 - dz)) ** n  # noqa: E731
    assert out["enabled"] is True
    assert out["twist"] == pytest.approx([shape(0.8), 0, shape(0.7), 0, 0, 0])
    pad["buttons"][5] = {"pressed": False, "value": 0}
    assert js(browser, f"JOG.gamepadTwist({json.dumps(pad)}, CFG.gamepad)")["enabled"] is False


def test_keyboard_keys_and_speed_scaling(browser):
    unit = js(browser, "JOG.keyboardTwist(new Set(['w', 'a', 'q', 'x']), CFG.keyboard)")
    assert unit == [1, 1, 0, 0, 0, 1]
    v = js(browser, "JOG.scaleTwist([1, 1, 0, 0, 0, 1], CFG, 0.5)")
    assert (v[0] ** 2 + v[1] ** 2) ** 0.5 == pytest.approx(0.05)  # a diagonal is capped too
    assert v[0] == pytest.approx(v[1]) and v[5] == pytest.approx(0.25)


def test_response_curve_properties_on_random_inputs(browser):
    rng = random.Random(3)
    xs = [rng.uniform(-1.5, 1.5) for _ in range(2000)] + [0.0, 0.12, -0.12, 1.0, -1.0]
    for dz, n in ((0.0, 1.0), (0.12, 2.0), (0.3, 3.5)):
        ys = js(browser, f"{json.dumps(xs)}.map((x) => JOG.shape(x, {dz}, {n}))")
        for x, y in zip(xs, ys, strict=True):
            assert -1 <= y <= 1
            if abs(x) <= dz:
                assert y == 0
            else:
                assert y * x > 0  # same sign as the input
                want = ((min(abs(x), 1) - dz) / (1 - dz)) ** n
                assert y == pytest.approx(want if x > 0 else -want)
        pairs = sorted(zip(xs, ys, strict=True))
        assert all(a[1] <= b[1] + 1e-12 for a, b in itertools.pairwise(pairs))  # monotonic


def test_holding_the_assist_sends_enables_and_letting_go_ends_it(browser):
    """Key g or the gamepad's A: arm_assist each tick while held, one arm_jog_end after."""
    pad = {"axes": [0, 0, 0, 0], "buttons": [{"pressed": True, "value": 1}]}
    assert js(browser, f"JOG.gamepadTwist({json.dumps(pad)}, CFG.gamepad)")["assist"] is True
    sent = js(
        browser,
        """(() => {
          const sent = [];
          const j = new JOG.Jogger(CFG, (m) => { sent.push(m.action); return true; });
          clearInterval(j.timer);
          j.keys.add(CFG.assist_key); j.tick(); j.tick();
          j.keys.add('w'); j.tick();  // a jog held beside it wins
          j.keys.clear(); j.tick(); j.tick();
          return sent;
        })()""",
    )
    assert sent == ["arm_assist", "arm_assist", "arm_jog", "arm_jog_end"]
