"""Arm jogs through the dashboard server, no browser: caps, checks, and every way a page stops."""

from __future__ import annotations

import dataclasses
import json
import math
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_dashboard_server import FakeNode, _next
from websockets.sync.client import connect

from common.config.typed import from_dict
from common.errors import ConfigError
from operator_side.dashboard import Dashboard, DashboardConfig
from operator_side.dashboard.jog_config import JogConfig, parse_mapping
from operator_side.dashboard.page_commands import cap_twist
from operator_side.dashboard.view import arm_view

pytestmark = [pytest.mark.timeout(30)]


class JogNode(FakeNode):
    control = None  # the control lease as the robot's heartbeat states it (None: unsigned)

    def __init__(self) -> None:
        super().__init__()
        self.ages_ms: list[float] = []

    def snapshot(self):
        return dataclasses.replace(super().snapshot(), control=self.control)

    stall_s = 0.0  # the next send_command blocks the server this long (a starved process)

    def send_command(self, action, grip_level=None, velocity=None, age_ms=0.0) -> None:
        self.commands.append((time.monotonic(), action, velocity))
        self.ages_ms.append(age_ms)
        stall, self.stall_s = self.stall_s, 0.0
        time.sleep(stall)

    def actions(self) -> list[str]:
        return [a for _, a, _ in self.commands]


@pytest.fixture
def dashboard():
    node = JogNode()
    d = Dashboard(node, DashboardConfig(port=0))
    d.start()
    try:
        yield node, d
    finally:
        d.stop()


def _page_ms() -> float:
    return time.monotonic() * 1000.0  # a page's performance.now(); its origin does not matter


def _jog(ws, velocity, t_page_ms: float | None = None) -> None:
    stamp = _page_ms() if t_page_ms is None else t_page_ms
    msg = {"type": "command", "action": "arm_jog", "velocity": velocity, "t_page_ms": stamp}
    ws.send(json.dumps(msg))


def test_jogs_are_capped_and_forwarded_and_bad_ones_refused(dashboard):
    node, d = dashboard
    with connect(d.ws_url) as ws:
        hello = _next(ws, "hello")
        assert hello["jog"]["gamepad"]["enable_button"] == 5
        _jog(ws, [1.0, 0, 0, 0, 0, 3.0])  # far over the caps
        for bad in ([0, 0, 0], [0, 0, 0, 0, 0, float("nan")], "fast", [True] * 6):
            ws.send(
                json.dumps(
                    {"type": "command", "action": "arm_jog", "velocity": bad, "t_page_ms": 1.0}
                ).replace("NaN", "1e999")
            )
            ack = _next(ws, "ack")
            assert not ack["ok"] and "velocity" in ack["error"]
        ws.send(json.dumps({"type": "command", "action": "arm_stop"}))
        assert _next(ws, "ack")["ok"]
    first = node.commands[0]
    assert first[1] == "arm_jog"
    assert first[2] == pytest.approx((0.10, 0, 0, 0, 0, 0.5))
    assert node.actions() == ["arm_jog", "arm_stop"]


def test_a_closed_page_that_was_jogging_stops_the_arm(dashboard):
    node, d = dashboard
    with connect(d.ws_url) as ws:
        _next(ws, "hello")
        _jog(ws, [0.02, 0, 0, 0, 0, 0])
        time.sleep(0.05)
    t_closed = time.monotonic()
    deadline = t_closed + 2
    while "arm_jog_end" not in node.actions():
        assert time.monotonic() < deadline, node.actions()
        time.sleep(0.01)
    stop_t = next(t for t, a, _ in node.commands if a == "arm_jog_end")
    assert stop_t - t_closed < 0.2
    assert "arm_stop" not in node.actions(), "a closed tab ends its jog; it is not a STOP"


def test_a_page_that_stops_sending_jogs_is_stopped_by_the_watchdog(dashboard):
    node, d = dashboard
    with connect(d.ws_url) as ws:
        _next(ws, "hello")
        _jog(ws, [0.02, 0, 0, 0, 0, 0])
        t_last = time.monotonic()
        deadline = t_last + 2
        while "arm_jog_end" not in node.actions():  # the socket stays open, the page is silent
            assert time.monotonic() < deadline
            time.sleep(0.01)
        stop_t = next(t for t, a, _ in node.commands if a == "arm_jog_end")
        # watchdog: six send periods at 30 Hz (200 ms), checked every quarter of that
        assert 0.15 < stop_t - t_last < 0.4


def test_jog_rate_is_limited_but_stop_never_is(dashboard):
    node, d = dashboard
    with connect(d.ws_url) as ws:
        _next(ws, "hello")
        for _ in range(100):
            _jog(ws, [0.01, 0, 0, 0, 0, 0])
        for _ in range(20):
            ws.send(json.dumps({"type": "command", "action": "arm_stop"}))
        refused = 0
        acks = 0
        while acks < 20:
            msg = _next(ws, "ack")
            if msg["action"] == "arm_jog":
                refused += 1
            else:
                acks += 1
                assert msg["ok"]
    assert node.actions().count("arm_jog") == 60  # twice the 30 Hz send rate, per second
    assert refused == 40
    assert node.actions().count("arm_stop") >= 20


def _sampled(d: Dashboard, control: dict) -> None:
    """Wait until the dashboard's sampler has taken the node's new control view."""
    deadline = time.monotonic() + 5
    while (d.push.latest or {}).get("control") != control:
        assert time.monotonic() < deadline, "the dashboard never sampled the node"
        time.sleep(0.01)


def test_resume_goes_to_the_robot_from_the_holder_and_is_refused_with_a_reason_otherwise(
    dashboard,
):
    node, d = dashboard
    with connect(d.ws_url) as ws:
        _next(ws, "hello")
        ws.send(json.dumps({"type": "command", "action": "arm_resume"}))
        assert _next(ws, "ack")["ok"], "unsigned: the one operator holds the arm"
        assert node.actions() == ["arm_resume"]
        node.control = {"ours": False, "holder": "a1b2c3", "pending": None}
        _sampled(d, node.control)
        ws.send(json.dumps({"type": "command", "action": "arm_resume"}))
        ack = _next(ws, "ack")
        assert not ack["ok"] and "a1b2c3… holds it" in ack["error"], ack
        node.control = {"ours": False, "holder": None, "pending": None}
        _sampled(d, node.control)
        ws.send(json.dumps({"type": "command", "action": "arm_resume"}))
        assert "ask for control" in _next(ws, "ack")["error"]
    assert node.actions() == ["arm_resume"], "a resume the robot would refuse is not sent"


@pytest.mark.slow
@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-10, 10), min_size=6, max_size=6))
def test_cap_twist_keeps_direction_and_never_exceeds_the_caps(v):
    out = cap_twist(v, 0.1, 0.5)
    for part, cap in ((slice(0, 3), 0.1), (slice(3, 6), 0.5)):
        n_in = math.hypot(*v[part])
        n_out = math.hypot(*out[part])
        assert n_out <= cap * (1 + 1e-9)
        if n_in <= cap:
            assert out[part] == pytest.approx(v[part])
        else:
            assert n_out == pytest.approx(cap)
            for a, b in zip(v[part], out[part], strict=True):
                assert a * b >= 0  # same direction


def test_mappings_and_keys_are_checked_when_the_config_loads():
    assert parse_mapping("button7-button6", ("axis", "button")) == [
        (1.0, "button", 7),
        (-1.0, "button", 6),
    ]
    for bad in (
        {"gamepad": {"mapping": ["axis9x", "", "", "", "", ""]}},
        {"gamepad": {"mapping": ["tx", "", "", "", "", ""]}},
        {"spacemouse": {"mapping": ["-ty"]}},
        {"keyboard": {"w": "forward"}},
        {"send_rate_hz": 1.0},
        {"gamepad": {"stop_button": 5}},  # the enable button
        {"gamepad": {"stop_button": 7}},  # a trigger in the default mapping
        {"gamepad": {"stop_button": 40}},
    ):
        with pytest.raises(ConfigError):
            from_dict(JogConfig, bad)


def test_arm_view_turns_heartbeat_stats_into_what_the_panel_shows():
    assert arm_view({"stimuli_published": 3.0}) is None
    stats = {
        "arm_x": 0.1,
        "arm_y": -0.2,
        "arm_z": 0.3,
        "arm_rx": math.pi,
        "arm_ry": 0.0,
        "arm_rz": 0.0,
        "arm_speed_m_s": 0.05,
        "arm_angular_speed_rad_s": 0.0,
        "arm_safety_mode": 3.0,
        "arm_program_running": 1.0,
        "arm_jogging": 0.0,
        "arm_deadman_stops": 2.0,
        "deadman_trips": 1.0,
        "arm_max_linear_m_s": 0.1,
        "arm_max_angular_rad_s": 0.5,
        **{f"arm_ws_{e}_{a}": (-0.4 if e == "min" else 0.4) for e in ("min", "max") for a in "xyz"},
    }
    view = arm_view(stats)
    assert view["pose"] == [100.0, -200.0, 300.0, 180.0, 0.0, 0.0]
    assert view["speed_mm_s"] == 50.0 and view["safety"] == "protective stop"
    assert view["program_running"] is True and view["deadman_stops"] == 2
    assert view["workspace_mm"] == [[-400.0] * 3, [400.0] * 3]
    assert view["stop_latched"] is False
    assert arm_view({**stats, "arm_stop_latched": 1.0})["stop_latched"] is True
    assert view["assist"] is None  # a robot without the assist says nothing of it
    turning = {**stats, "assist_phase": 4.0, "assist_regrasps": 1.0, "assist_steps": 9.0}
    assert arm_view(turning)["assist"] == {"phase": "turn", "regrasps": 1, "steps": 9}


def test_the_assist_is_held_like_a_jog_forwarded_and_ended_by_the_watchdog(dashboard):
    """A page holding the assist sends enables; gone quiet, the watchdog ends it as a jog."""
    node, d = dashboard
    with connect(d.ws_url) as ws:
        hello = _next(ws, "hello")
        assert hello["jog"]["assist_key"] == "g" and hello["jog"]["gamepad"]["assist_button"] == 0
        for _ in range(3):
            ws.send(
                json.dumps({"type": "command", "action": "arm_assist", "t_page_ms": _page_ms()})
            )
        t_last = time.monotonic()
        deadline = t_last + 2
        while "arm_jog_end" not in node.actions():  # the socket stays open, the page is silent
            assert time.monotonic() < deadline, node.actions()
            time.sleep(0.01)
    assert node.actions()[:4] == ["arm_assist"] * 3 + ["arm_jog_end"]
    assert d.commands.assists_forwarded == 3


def test_the_assist_key_and_button_must_move_nothing_else():
    with pytest.raises(ValueError, match="assist_key"):
        JogConfig(assist_key="w")
    with pytest.raises(ValueError, match="assist_button"):
        from_dict(JogConfig, {"gamepad": {"assist_button": 5}}, where="jog")


def test_a_jog_without_the_pages_clock_is_refused(dashboard):
    node, d = dashboard
    with connect(d.ws_url) as ws:
        _next(ws, "hello")
        for stamp in (None, "now", float("nan"), True):
            msg = {"type": "command", "action": "arm_jog", "velocity": [0.02, 0, 0, 0, 0, 0]}
            if stamp is not None:
                msg["t_page_ms"] = stamp
            ws.send(json.dumps(msg).replace("NaN", "1e999"))
            ack = _next(ws, "ack")
            assert not ack["ok"] and "t_page_ms" in ack["error"], (stamp, ack)
        ws.send(json.dumps({"type": "command", "action": "arm_assist"}))
        assert "t_page_ms" in _next(ws, "ack")["error"]
    assert "arm_jog" not in node.actions() and "arm_assist" not in node.actions()


def test_jogs_that_waited_behind_a_stalled_server_are_handed_on_with_their_age(dashboard):
    """The server stalls (a starved operator PC) while the page keeps jogging: the jogs
    that queued up reach the node with the time they waited, so it can drop them."""
    node, d = dashboard
    with connect(d.ws_url) as ws:
        _next(ws, "hello")
        origin = 5_000_000.0 - _page_ms()  # the page's clock has its own origin
        _jog(ws, [0.02, 0, 0, 0, 0, 0], _page_ms() + origin)
        deadline = time.monotonic() + 2
        while not node.actions():
            assert time.monotonic() < deadline
            time.sleep(0.005)
        node.stall_s = 0.5
        _jog(ws, [0.02, 0, 0, 0, 0, 0], _page_ms() + origin)  # this one stalls the server
        for _ in range(6):
            time.sleep(0.033)
            _jog(ws, [0.02, 0, 0, 0, 0, 0], _page_ms() + origin)
        while len(node.actions()) < 8:
            assert time.monotonic() < deadline + 2, node.actions()
            time.sleep(0.01)
    ages = node.ages_ms[:8]
    assert max(ages[:2]) < 50, ages  # on time
    queued = ages[2:]
    # each waited for the rest of the stall: about 0.5 s less its send time (33 ms apart)
    assert all(250 < a < 700 for a in queued), ages
    assert queued == sorted(queued, reverse=True), ages


@settings(max_examples=200, deadline=None)
@given(
    offset_ms=st.floats(-1e9, 1e9),
    drift_ppm=st.floats(-500, 500),
    jitter_ms=st.lists(st.floats(0, 20), min_size=50, max_size=50),
    gap_s=st.floats(0.01, 3600),
    stall_ms=st.floats(200, 5000),
)
def test_the_page_clock_sees_a_stall_whatever_the_pages_offset_and_drift(
    offset_ms, drift_ppm, jitter_ms, gap_s, stall_ms
):
    """Fresh messages never look late, over an hour's silence and any offset or drift under
    500 ppm; a message that waited ``stall_ms`` shows (almost) all of it."""
    from operator_side.dashboard.page_commands import PageClock

    clock = PageClock()
    rate = 1 + drift_ppm * 1e-6

    def page(t_ms: float) -> float:
        return t_ms * rate + offset_ms

    t = 1000.0
    for j in jitter_ms:  # a second and a half of jogs, each 0-20 ms in transit
        t += 33.0
        assert clock.delay_ms(page(t), t + j) <= 20.0 + 1e-6
    t += gap_s * 1000.0  # the operator lets go; the page is quiet
    for j in jitter_ms[:5]:
        t += 33.0
        assert clock.delay_ms(page(t), t + j) <= 20.0 + 0.5 * 1e-3 * gap_s * 1000 + 1e-6
    t += 33.0
    late = clock.delay_ms(page(t), t + stall_ms)
    assert late >= stall_ms - 20.0 - 1e-6, late


def test_a_stop_with_a_bad_page_stamp_still_stops(dashboard):
    node, d = dashboard
    with connect(d.ws_url) as ws:
        _next(ws, "hello")
        ws.send(json.dumps({"type": "command", "action": "arm_stop", "t_page_ms": "soon"}))
        assert _next(ws, "ack")["ok"]
    assert node.actions() == ["arm_stop"]
