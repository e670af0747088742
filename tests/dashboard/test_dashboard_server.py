"""The dashboard without a browser: what it pushes, what it refuses, how it counts the link."""

from __future__ import annotations

import contextlib
import json
import threading
import time
import urllib.error
import urllib.request
from http.cookiejar import CookieJar

import numpy as np
import pytest
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from common.tactile.contract import MASKS
from operator_side.dashboard import Dashboard, DashboardConfig
from operator_side.dashboard.snapshot import Snapshot
from operator_side.dashboard.view import LinkHistory, snapshot_view
from operator_side.node.config import OperatorConfig
from operator_side.palm.renderer import LinkGlideRenderer
from operator_side.servos.calibration import LinkGlideCalibration

pytestmark = [
    pytest.mark.timeout(30),
    # the dashboard here stands for the operator node's own (its threads at the operator unit's
    # niceness, -10), not for a test process at -5 below three lanes' nodes: starved there, "a
    # change goes out at once" took 116 ms and the push rate read a backlog
    pytest.mark.usefixtures("robot_node_priority_module"),
]


class FakeNode:
    """The two calls the dashboard makes; a stimulus the test sets; commands it records."""

    def __init__(self) -> None:
        self.config = OperatorConfig()
        self.calibration = LinkGlideCalibration()
        self.renderer = LinkGlideRenderer(self.config.renderer, self.calibration)
        self.stimulus: np.ndarray | None = None
        self.robot_stats: dict[str, float] = {}
        self.stats: dict[str, float] = {}
        self.commands: list[tuple] = []
        self.lock = threading.Lock()

    def snapshot(self) -> Snapshot:
        with self.lock:
            counts = self.renderer.target_counts(self.stimulus)
            return Snapshot(
                link_state="ok" if self.stimulus is not None else "down",
                stimulus=self.stimulus,
                pattern=None,
                confidence=None,
                grip_level=None,
                frame=None,
                goal_counts=counts,
                goal_angles=self.calibration.counts_to_angles(counts),
                age_ms=5.0 if self.stimulus is not None else None,
                stats=dict(self.stats),
                robot_stats=dict(self.robot_stats),
            )

    def send_command(self, action, grip_level=None, velocity=None, age_ms=0.0) -> None:
        self.commands.append((action, grip_level))


def _snap(age_ms: float | None, sent: float | None, received: float) -> Snapshot:
    return Snapshot(
        link_state="ok",
        stimulus=None,
        pattern=None,
        confidence=None,
        grip_level=None,
        frame=None,
        goal_counts=np.zeros(6, dtype=np.int64),
        goal_angles=np.zeros((3, 2)),
        age_ms=age_ms,
        stats={"stimuli_received": received},
        robot_stats={} if sent is None else {"stimuli_published": sent, "keyframes": 0.0},
    )


@pytest.fixture
def dashboard():
    node = FakeNode()
    d = Dashboard(node, DashboardConfig(port=0, max_rate_hz=120))
    d.start()
    try:
        yield node, d
    finally:
        d.stop()


def _next(ws, kind: str, timeout_s: float = 2.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while True:
        msg = json.loads(ws.recv(timeout=max(0.01, deadline - time.monotonic())))
        if msg["type"] == kind:
            return msg


@pytest.mark.slow
def test_pushes_only_when_something_changed_and_refreshes_slowly_otherwise(dashboard):
    node, d = dashboard
    with connect(d.ws_url) as ws:
        hello = _next(ws, "hello")
        assert hello["geometry"]["l1"] == 20.0 and len(hello["patterns"]) == 12
        assert hello["patterns"][5]["cells"] == [[1, 2], [2, 1]]
        _next(ws, "state")
        # Nothing changes: at 120 Hz sampling, only the 4 Hz refresh goes out.
        t0, n, samples0 = time.monotonic(), 0, d.push.samples
        while time.monotonic() - t0 < 1.0:
            _next(ws, "state")
            n += 1
        assert 2 <= n <= 7, f"{n} pushes in a second with nothing changing"
        # sampled far more often than pushed (not at 120 Hz: a fresh clone's deployment lane
        # starved this process to 65 samples in its first second and more)
        sampled = d.push.samples - samples0
        assert sampled > 3 * n, f"{sampled} samples against {n} pushes"
        # A change goes out at once.
        with node.lock:
            node.stimulus = (MASKS[9] * 4.0).astype(np.float32)
        t_change = time.monotonic()
        while True:
            msg = _next(ws, "state")
            if msg["stimulus"] is not None:
                break
        assert time.monotonic() - t_change < 0.1
        assert msg["stimulus"] == (MASKS[9] * 4.0).tolist()
        assert msg["counts"] == node.renderer.target_counts(node.stimulus).tolist()


@pytest.mark.slow
def test_a_stimulus_changing_at_every_sample_reaches_a_page_at_the_push_rate(dashboard):
    """Sampled at 120 Hz for the history; pushed at 30 (the page's redraws); none without a page."""
    node, d = dashboard
    stop = threading.Event()

    def change() -> None:  # a new stimulus every 2 ms: every sample sees a change
        level = 0
        while not stop.is_set():
            level = level % 9 + 1
            with node.lock:
                node.stimulus = (MASKS[9] * float(level)).astype(np.float32)
            time.sleep(0.002)

    changer = threading.Thread(target=change, daemon=True)
    changer.start()
    try:
        samples0, pushes0 = d.push.samples, d.push.pushes
        # 40 samples take a third of a second at 120 Hz; a clean clone's deployment lane
        # starved this process to 34 in half a second: the rate is not what is asserted here
        deadline = time.monotonic() + 5.0
        while d.push.samples - samples0 <= 40 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert d.push.samples - samples0 > 40, "the history is sampled with no page open"
        assert d.push.pushes == pushes0, "states were pushed with no page open"
        with connect(d.ws_url) as ws:
            _next(ws, "hello")
            _next(ws, "state")
            # the window starts with nothing queued: states pushed while this thread was not
            # reading (a fresh clone's test read 33 in its second) were pushed before it
            with contextlib.suppress(TimeoutError):
                while True:
                    ws.recv(timeout=0)
            t0, n = time.monotonic(), 0
            samples0 = d.push.samples
            while time.monotonic() - t0 < 1.0:
                _next(ws, "state")
                n += 1
            sampled = d.push.samples - samples0
    finally:
        stop.set()
        changer.join()
    push_hz = d.config.push_rate_hz
    assert 0.6 * push_hz <= n <= push_hz + 2, f"{n} states in a second, push rate {push_hz}"
    assert sampled > 2 * n, f"{sampled} samples against {n} pushes"


def test_commands_are_checked_before_they_reach_the_node(dashboard):
    node, d = dashboard
    with connect(d.ws_url) as ws:
        _next(ws, "hello")
        for msg, ok in [
            ({"type": "command", "action": "gripper_close", "grip_level": 31}, True),
            ({"type": "command", "action": "gripper_open"}, True),
            ({"type": "command", "action": "gripper_close", "grip_level": 0}, False),
            ({"type": "command", "action": "gripper_close", "grip_level": "9"}, False),
            ({"type": "command", "action": "arm_jog"}, False),
            ({"type": "hello"}, False),
        ]:
            ws.send(json.dumps(msg))
            assert _next(ws, "ack")["ok"] is ok, msg
        ws.send("not json")
        assert _next(ws, "ack")["ok"] is False
        # A flood is cut at 10 per second.
        for _ in range(12):
            ws.send(json.dumps({"type": "command", "action": "gripper_open"}))
        acks = [_next(ws, "ack")["ok"] for _ in range(12)]
        assert acks.count(True) == 8  # 2 above + 8 = 10 in this second
    assert node.commands[:2] == [("gripper_close", 31), ("gripper_open", None)]
    assert len(node.commands) == 10


def test_another_sites_page_cannot_open_the_socket(dashboard):
    _, d = dashboard
    with (
        pytest.raises(InvalidStatus) as e,
        connect(d.ws_url, origin="http://evil.example"),
    ):
        pass
    assert e.value.response.status_code == 403
    host = d.url.removeprefix("http://").rstrip("/")
    with connect(d.ws_url, origin=f"http://{host}") as ws:
        assert _next(ws, "hello")


def browser_like_opener() -> urllib.request.OpenerDirector:
    """Follows redirects and keeps cookies, as a browser does."""
    return urllib.request.build_opener(urllib.request.HTTPCookieProcessor(CookieJar()))


def test_serves_its_own_files_with_a_same_origin_policy(dashboard):
    _, d = dashboard
    browser = browser_like_opener()
    with browser.open(d.url, timeout=2) as r:
        page = r.read().decode()
        assert "default-src 'self'" in r.headers["Content-Security-Policy"]
    assert '<script src="/app.js">' in page and "http" not in page.split("<body>")[1]
    for name in ("app.js", "patterns.js", "style.css"):
        with browser.open(d.server.base_url + name, timeout=2) as r:
            assert r.status == 200
    with pytest.raises(urllib.error.HTTPError) as e:
        browser.open(d.server.base_url + "../operator_side/node.py", timeout=2)
    assert e.value.code == 404
    e.value.close()


def test_a_taken_port_is_a_config_error_naming_it(dashboard):
    from common.errors import ConfigError

    _, d = dashboard
    other = Dashboard(FakeNode(), DashboardConfig(port=d.server.port))
    with pytest.raises(ConfigError, match=str(d.server.port)):
        other.start()


def test_snapshot_view_is_small_json():
    node = FakeNode()
    node.stimulus = (MASKS[3] * 2.5).astype(np.float32)
    view = snapshot_view(node.snapshot())
    text = json.dumps(view)
    assert view["stimulus"][0][2] == 2.5 and view["link_state"] == "ok"
    assert len(text) < 1000


def test_history_latency_is_the_youngest_age_in_each_second():
    h = LinkHistory()
    for i, age in enumerate([30.0, 12.0, 50.0]):
        h.add(100.0 + i * 0.3, _snap(age, None, 0))
    h.add(101.0, _snap(40.0, None, 0))
    v = h.view()
    assert v["latency_ms"] == [12.0, 40.0]
    assert v["loss"] == [None, None] and v["summary"]["loss"] is None


def test_history_loss_ignores_in_flight_noise_but_keeps_real_losses():
    h = LinkHistory()
    # Ten seconds at 60/s, heartbeats at 20/s; the pairing drifts by one
    # message back and forth; early in second 6, six messages are really lost.
    for second in range(10):
        for k in range(20):
            sent = second * 60 + (k + 1) * 3
            lost_so_far = 0 if second < 6 else 6 if second > 6 else min(6, 3 * (k + 1))
            received_now = sent - lost_so_far
            jitter = 1 if (second + k) % 7 == 0 else 0
            received = received_now + jitter
            t = second + k / 20
            h.add(t, _snap(5.0, float(sent), float(received)))
    v = h.view()
    lost = h.lost_per_bucket()
    assert sum(lost) == pytest.approx(6, abs=1)
    assert lost[6] == pytest.approx(6, abs=1)
    # The first pairing's own drift is the only error left: one message at most.
    assert sum(x for i, x in enumerate(lost) if i != 6) <= 1
    assert v["summary"]["loss"] == pytest.approx(6 / v["summary"]["sent"], abs=2e-3)


def test_history_keeps_one_minute_and_survives_a_robot_restart():
    h = LinkHistory()
    for s in range(90):
        sent = (s % 50) * 10 + 10  # the robot restarts at s = 50: counters fall
        h.add(float(s), _snap(5.0, float(sent), float(sent)))
    v = h.view()
    assert len(v["latency_ms"]) == 60
    assert v["t"][0] == -59 and v["t"][-1] == 0
    assert v["summary"]["loss"] == 0.0


def test_the_control_lease_buttons_reach_the_node_and_the_lease_is_shown(dashboard):
    node, d = dashboard
    control = {"ours": False, "holder": "ab12", "pending": None, "asked": False, "key": "cd34"}
    original = node.snapshot

    def with_control() -> Snapshot:
        snap = original()
        snap.control = control
        return snap

    node.snapshot = with_control
    with connect(d.ws_url) as ws:
        _next(ws, "hello")
        # the first state may come from a snapshot taken before the patch; a change is pushed
        deadline = time.monotonic() + 3.0
        while _next(ws, "state").get("control") != control:
            assert time.monotonic() < deadline, "the lease never reached the page"
        for action in ("lease_request", "lease_grant", "lease_release"):
            ws.send(json.dumps({"type": "command", "action": action}))
            assert _next(ws, "ack")["ok"] is True
    assert [a for a, _ in node.commands] == ["lease_request", "lease_grant", "lease_release"]
