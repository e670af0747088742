"""Jogging the simulated arm from the dashboard in headless chromium, with injected devices.

The whole path runs for real: the page reads an injected gamepad (its
``navigator.getGamepads`` replaced) or raw SpaceMouse HID reports (fed to
the same handler a WebHID device's ``inputreport`` events reach), shapes
them, and sends jogs over its WebSocket; the dashboard server hands them to
the operator node's command sender; the robot node applies them through the
arm interface's clipping and deadman to ur-rtde, which drives the UR
simulator. Motion and standstill are read from the simulator itself.

The arm's path runs as deployed: the robot node is its own process (at its
unit's priority) and the UR simulator another, so the driver's watchdog kicks
share an interpreter with the robot node alone; the operator node and its
dashboard are a process of their own too, at their unit's priority.
"""

from __future__ import annotations

import contextlib
import json
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
from headless_chromium import Chromium, needs_chromium

from harness.bench.command_path import RobotUnderCommands
from harness.headless_chromium import PAGE_WAIT_S
from harness.operator_process import OperatorWithDashboard
from robot_side.arm.sim import URSimProcess

pytestmark = [
    pytest.mark.slow,
    pytest.mark.timeout(120),
    needs_chromium,
]

STOP_WITHIN_S = 0.4
#: the page's arm pose is one the simulator had at most this long ago
SHOWN_WITHIN_S = 0.5
STILL_M_S = 1e-4  # the simulator reports exactly zero at standstill; allow rounding
STILL_RAD_S = 1e-3
SPEED_SCALE = 0.3  # the page's default: 30 % of the operator's 0.10 m/s cap

PAD = """
(() => {
  const pad = { index: 0, id: "injected test pad", connected: true, mapping: "standard",
    axes: [0, 0, 0, 0],
    buttons: Array.from({ length: 17 }, () => ({ pressed: false, touched: false, value: 0 })) };
  window.__pad = pad;
  Object.defineProperty(navigator, "getGamepads",
    { configurable: true, value: () => [window.__pad] });
  return true;
})()
"""


def hid(report_id: int, values: list[int], fmt: str = "<6h") -> str:
    """JS that feeds one raw SpaceMouse report to the page's WebHID handler."""
    import struct

    raw = list(struct.pack(fmt, *values))
    return f"dxp.jog.hidReport({report_id}, new Uint8Array({json.dumps(raw)}))"


@pytest.fixture(scope="module")
def station(tmp_path_factory, quiet_gc_module):
    with running_station(tmp_path_factory.mktemp("arm-jog")) as both:
        yield both


@contextlib.contextmanager
def running_station(
    workdir: Path, max_command_age_ms: float | None = None
) -> Iterator[tuple[RobotUnderCommands, OperatorWithDashboard]]:
    """The robot node and the operator node with its dashboard, each as deployed.

    Each node is its own process at its unit's priority, and the UR simulator
    another (``RobotUnderCommands``, ``OperatorWithDashboard``): the thread
    that kicks the controller's watchdog shares its interpreter with the robot
    node alone, and the dashboard's with the operator node alone, as on the
    robot's and the operator's PCs, never with this process's browser driver
    and probes. Motion is read from the simulator.
    """
    settings: tuple[str, ...] = ()
    if max_command_age_ms is not None:
        settings += (f"robot.link.max_command_age_ms={max_command_age_ms}",)
    with RobotUnderCommands(workdir, settings) as rig:
        deadline = time.monotonic() + 30
        while rig.arm_sim.stats()["watchdog_hz"] is None:  # the driver armed it: connected
            assert time.monotonic() < deadline, (
                f"the arm never connected:\n{rig.log.read_text()[-3000:]}"
            )
            time.sleep(0.05)
        with OperatorWithDashboard(
            workdir, rig.telemetry_endpoint, rig.command_endpoint
        ) as operator:
            yield rig, operator


@pytest.fixture
def page(station):
    rig, dashboard = station
    with Chromium(width=1280, height=1000) as browser:
        browser.navigate(dashboard.url)
        browser.wait_for("dxp.jog !== null && dxp.state.arm && dxp.state.arm.pose", 20)
        # a page that says "reconnecting" (the arm recovering from a watchdog trip) is waited out
        browser.wait_for("dxp.state.arm.available", 20)
        yield browser, rig
        assert browser.page_errors() == []


@contextlib.contextmanager
def watchdog_trips_named(rig: RobotUnderCommands):
    """A failed motion check says whether the controller's own watchdog stopped the arm.

    The controller stops the program when the driver's kicks stop for its watchdog window
    (docs/arm.md); the driver then reconnects. That is a stop the operator did not ask for,
    so it fails the test, with the trips and the driver's own account of its silences (its
    log) named, so the message says which failure it was.
    """
    trips0 = rig.arm_sim.stats()["watchdog_trips"]
    try:
        yield
    except AssertionError as e:
        trips = rig.arm_sim.stats()["watchdog_trips"] - trips0
        if trips:
            said = [
                f"{line.level} {line.message}" for line in rig.log_lines("robot_side.arm.ur_rtde")
            ]
            raise AssertionError(
                f"the controller's watchdog tripped {trips}x during the check (the driver's "
                f"kicks stopped for the watchdog window; the driver said: {said[-6:]}): {e}"
            ) from e
        raise


def speed(sim: URSimProcess) -> float:
    return float(np.linalg.norm(sim.tcp_speed()[:3]))


def wait_still(sim: URSimProcess, timeout_s: float = 3.0) -> float:
    """Seconds until the simulator's TCP is at standstill (printed: pytest -s shows them)."""
    t0 = time.monotonic()
    while speed(sim) > STILL_M_S or np.linalg.norm(sim.tcp_speed()[3:]) > STILL_RAD_S:
        assert time.monotonic() - t0 < timeout_s, "the arm never stopped"
        time.sleep(0.005)
    took = time.monotonic() - t0
    print(f"standstill after {took * 1000:.0f} ms")
    return took


def stop_took(sim: URSimProcess, t0: float) -> float:
    """Seconds from ``t0`` until the arm came to rest for good, by the simulator's own record.

    Read once the stop budget has passed: on a busy machine the jogs arrive sparse and the
    deadman stops the arm between them, so the arm may be still at ``t0`` and move once more
    for a jog sent before it, until the stop sent at ``t0`` arrives (it was read as "moved
    again" 18 ms after a release). A test process starved while it watched must not read as
    a late stop either (one read "standstill after 467 ms" beside a jog the same starved
    process had dropped as 276 ms old)."""
    time.sleep(max(0.0, t0 + STOP_WITHIN_S - time.monotonic()))
    wait_still(sim)
    since = sim.at_rest_since(STILL_M_S, STILL_RAD_S)
    assert since is not None, "the arm moved again after it stopped"
    print(f"at rest {(since - t0) * 1000:.0f} ms after, by the simulator's record")
    return since - t0


def move_until(
    sim: URSimProcess, reached: Callable[[np.ndarray], bool], timeout_s: float = 5.0
) -> tuple[np.ndarray, float]:
    """(pose change, top linear speed) once ``reached(change)`` holds, or at ``timeout_s``.

    A second of jogging covers 30 mm on a quiet machine; on a saturated one the page and
    the nodes send and admit fewer jogs and the deadman stops the arm between them, so
    the distance is waited for (the speed checks that follow stay exact).
    """
    start = sim.tcp_pose()
    top = 0.0
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        top = max(top, speed(sim))
        if reached(sim.tcp_pose() - start):
            break
        time.sleep(0.02)
    return sim.tcp_pose() - start, top


def move_for(sim: URSimProcess, seconds: float) -> tuple[np.ndarray, float]:
    """(pose change, top linear speed) over ``seconds`` of an already commanded jog."""
    start = sim.tcp_pose()
    top = 0.0
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        top = max(top, speed(sim))
        time.sleep(0.02)
    return sim.tcp_pose() - start, top


#: the robot's counters that say why a held jog moved the arm less than it should have
JOG_COUNTERS = (
    "commands_received",
    "commands_stale",
    "commands_unsynced",
    "commands_from_future",
    "arm_deadman_stops",
    "deadman_trips",
    "arm_stop_latched",
)


def robot_said(rig: RobotUnderCommands, before: dict[str, float]) -> dict[str, float]:
    """The change in the robot's jog counters since ``before`` (its heartbeats' stats): a
    failed distance check says whether the jogs arrived, aged out or were cut by the
    deadman, instead of only how far the arm went."""
    now = rig.telemetry.robot_stats()
    return {k: now.get(k, 0.0) - before.get(k, 0.0) for k in JOG_COUNTERS if k in now}


def page_follows_the_arm(browser: Chromium, sim: URSimProcess, for_s: float = 3.0) -> None:
    """The page's x is one the simulator had at most ``SHOWN_WITHIN_S`` before the page was read.

    The simulator is watched for ``SHOWN_WITHIN_S`` before the first read, so every pose the
    page may rightly show is in the history. Read again for up to ``for_s``, and at least
    three times (a starved browser can take seconds to answer one read), while the arm moves:
    a page that fell behind while this process (its operator node and dashboard) was starved
    must catch up; one that never shows the simulator's pose (a stale view, the wrong axis or
    unit) fails with each read.
    """
    history: list[tuple[float, float]] = []  # (monotonic s, the simulator's x in m)

    def watch(seconds: float) -> None:
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end:
            history.append((time.monotonic(), sim.tcp_pose()[0]))
            time.sleep(0.02)

    reads = []
    watch(SHOWN_WITHIN_S)
    t_start = time.monotonic()
    while time.monotonic() < t_start + for_s or len(reads) < 3:
        t_asked = time.monotonic()
        shown = browser.evaluate("dxp.state.arm.pose[0]") / 1000
        t_answered = time.monotonic()
        history.append((t_answered, sim.tcp_pose()[0]))
        had = [x for t, x in history if t >= t_asked - SHOWN_WITHIN_S]
        if min(had) - 0.001 <= shown <= max(had) + 0.001:
            return
        reads.append(
            (round(t_asked - t_start, 2), round(t_answered - t_asked, 2), shown, min(had), max(had))
        )
        watch(0.1)  # 100 ms of the simulator between reads of the page
    raise AssertionError(
        f"the page never showed a pose the simulator had in the {SHOWN_WITHIN_S} s before: "
        f"(s into the check, s the read took, shown x, the simulator's x range) {reads}"
    )


def test_gamepad_moves_the_arm_only_while_enable_is_held_and_stops_on_release(page):
    browser, rig = page
    with watchdog_trips_named(rig):
        _gamepad_moves_the_arm_only_while_enable_is_held(browser, rig)


def _gamepad_moves_the_arm_only_while_enable_is_held(browser: Chromium, rig: RobotUnderCommands):
    sim = rig.arm_sim
    wait_still(sim)
    browser.evaluate(PAD)
    # stick pushed forward, enable not held: nothing may move
    browser.evaluate("window.__pad.axes[1] = -1.0")
    delta, top = move_for(sim, 0.4)
    assert top < STILL_M_S and np.linalg.norm(delta[:3]) < 1e-4
    # enable held: +x at the speed scale, nothing else
    browser.evaluate("window.__pad.buttons[5] = { pressed: true, touched: true, value: 1 }")
    browser.wait_until("dxp.jog.moving", bool)
    before = rig.telemetry.robot_stats()
    delta, top = move_until(sim, lambda d: d[0] > 0.03)
    assert delta[0] > 0.015, (delta, robot_said(rig, before))
    assert abs(delta[1]) < 0.1 * delta[0] and abs(delta[2]) < 0.1 * delta[0], delta
    assert top <= SPEED_SCALE * 0.10 * 1.02, top  # within the scaled cap
    assert top > SPEED_SCALE * 0.10 * 0.8, top  # and really at it
    # the page shows the arm moving where the simulator has it
    page_follows_the_arm(browser, sim)
    # release: standstill within 400 ms
    browser.evaluate("window.__pad.buttons[5] = { pressed: false, touched: false, value: 0 }")
    t_release = time.monotonic()
    took = stop_took(sim, t_release)
    assert took < STOP_WITHIN_S, f"the arm came to rest {took * 1e3:.0f} ms after the release"
    # wrist rotation from the right stick
    browser.evaluate("window.__pad.axes[1] = 0; window.__pad.axes[2] = -1.0")
    browser.evaluate("window.__pad.buttons[5] = { pressed: true, touched: true, value: 1 }")
    browser.wait_until("dxp.jog.moving", bool)
    top_w, top_v = 0.0, 0.0
    samples = []  # (s from the enable, the simulator's TCP speed): what a failure shows
    t0 = time.monotonic()  # 0.6 s at least; up to 5 s for a starved process to reach speed
    while time.monotonic() - t0 < 0.6 or (
        top_w <= SPEED_SCALE * 0.5 * 0.8 and time.monotonic() - t0 < 5.0
    ):
        w = sim.tcp_speed()
        samples.append((round(time.monotonic() - t0, 3), np.round(w, 4).tolist()))
        top_w, top_v = max(top_w, w[5]), max(top_v, float(np.linalg.norm(w[:3])))
        time.sleep(0.02)
    assert SPEED_SCALE * 0.5 * 0.8 < top_w <= SPEED_SCALE * 0.5 * 1.02, top_w  # +wz, scaled
    # the wrist turns, the TCP stays put (a clean-clone run once read 2.0 mm/s: the samples
    # say when)
    assert top_v < 1e-3, (top_v, samples[:12])
    browser.evaluate("window.__pad.buttons[5] = { pressed: false, touched: false, value: 0 }")
    t_release = time.monotonic()
    took = stop_took(sim, t_release)
    assert took < STOP_WITHIN_S, f"the arm came to rest {took * 1e3:.0f} ms after the release"


def test_spacemouse_reports_move_the_arm_and_its_button_release_stops_it(page):
    browser, rig = page
    with watchdog_trips_named(rig):
        _spacemouse_moves_the_arm(browser, rig)


def _spacemouse_moves_the_arm(browser: Chromium, rig: RobotUnderCommands):
    sim = rig.arm_sim
    wait_still(sim)
    # a newer SpaceMouse: one 12-byte report, cap pushed away (ty -350) and lifted (tz -350)
    browser.evaluate(hid(1, [0, -350, -350, 0, 0, 0]))
    delta, top = move_for(sim, 0.3)
    assert top < STILL_M_S, "moved without the enable button"
    browser.evaluate(hid(3, [1], "<B"))  # left button down
    browser.wait_until("dxp.jog.moving", bool)
    before = rig.telemetry.robot_stats()
    delta, top = move_until(sim, lambda d: d[0] > 0.02 and d[2] > 0.02)
    assert delta[0] > 0.01 and delta[2] > 0.01, (delta, robot_said(rig, before))  # +x and +z
    assert abs(delta[1]) < 0.1 * delta[0], delta
    assert top <= SPEED_SCALE * 0.10 * 1.02, top  # the scale caps the combined speed
    browser.evaluate(hid(3, [0], "<B"))
    t_release = time.monotonic()
    took = stop_took(sim, t_release)
    assert took < STOP_WITHIN_S, f"the arm came to rest {took * 1e3:.0f} ms after the release"
    browser.evaluate(hid(1, [0, 0, 0, 0, 0, 0]))


def jog_right_with_the_pad(browser: Chromium, sim: URSimProcess) -> None:
    """The injected gamepad's stick right (-y) with its enable held, until the TCP is at speed."""
    wait_still(sim)
    browser.evaluate(PAD)
    browser.evaluate(
        "window.__pad.axes[0] = 1.0;"  # stick right: -y
        "window.__pad.buttons[5] = { pressed: true, touched: true, value: 1 }"
    )
    browser.wait_until("dxp.jog.moving", bool)
    # moving -y at speed (a starved simulator makes the driver refuse jogs for a while)
    deadline = time.monotonic() + 5
    while sim.tcp_speed()[1] > -0.8 * SPEED_SCALE * 0.10:
        assert time.monotonic() < deadline, sim.tcp_speed()
        time.sleep(0.01)


def test_closing_the_tab_stops_the_arm(station):
    rig, dashboard = station
    sim = rig.arm_sim
    with Chromium(width=1280, height=1000) as browser, watchdog_trips_named(rig):
        browser.navigate(dashboard.url)
        browser.wait_for("dxp.jog !== null && dxp.state.arm && dxp.state.arm.pose", 20)
        browser.wait_for("dxp.state.arm.available", 20)
        jog_right_with_the_pad(browser, sim)
        t_close, wall_close = time.monotonic(), time.time()
        browser.ws.send(json.dumps({"id": 10**6, "method": "Page.close", "params": {}}))
        took = stop_took(sim, t_close)
        # when the dashboard heard the page let go or its socket close, by its log
        lines = [
            line
            for line in dashboard.log_lines("operator_side.dashboard")
            if line.created >= wall_close - 0.5
        ]
        seen = [f"{(line.created - wall_close) * 1e3:+.0f} ms {line.message}" for line in lines]
        if took < STOP_WITHIN_S:
            return
        # The page lets go when its browser runs its pagehide, or its socket closes; until
        # then it is a page whose user holds the stick. A renderer starved of the CPU ran it
        # 452 ms after the close (jogging on meanwhile, the pad still held): the browser's
        # wait. From there the product's budget holds as from the close.
        ends = [
            line.created - wall_close
            for line in lines
            if line.created >= wall_close
            and ("released on the page" in line.message or "page disconnected" in line.message)
        ]
        assert ends, (
            f"the arm came to rest {took * 1e3:.0f} ms after the close; the dashboard: {seen}"
        )
        assert took - ends[0] < STOP_WITHIN_S, (
            f"the arm came to rest {(took - ends[0]) * 1e3:.0f} ms after the page let go "
            f"({took * 1e3:.0f} ms after the close); the dashboard: {seen}"
        )
        print(f"the page let go {ends[0] * 1e3:.0f} ms after the close; at rest {took * 1e3:.0f}")


def test_a_hidden_page_stops_the_arm_and_its_held_gamepad_moves_nothing(page):
    """A tab hidden (or being left) ends the jog, and the gamepad its user still holds, read
    again at every tick until the page is gone, does not start it again."""
    browser, rig = page
    sim = rig.arm_sim
    with watchdog_trips_named(rig):
        jog_right_with_the_pad(browser, sim)
        browser.evaluate("window.dispatchEvent(new PageTransitionEvent('pagehide'))")
        t_hidden = time.monotonic()
        took = stop_took(sim, t_hidden)
        assert took < STOP_WITHIN_S, f"the arm came to rest {took * 1e3:.0f} ms after the hide"
        time.sleep(0.5)  # 15 ticks of the page with the pad still held
        assert sim.at_rest_since(STILL_M_S, STILL_RAD_S) is not None, "the held pad moved it"
        assert not browser.evaluate("dxp.jog.moving")
        # shown again: the same held pad jogs again
        browser.evaluate("window.dispatchEvent(new PageTransitionEvent('pageshow'))")
        browser.wait_until("dxp.jog.moving", bool)
        browser.evaluate("window.__pad.buttons[5] = { pressed: false, touched: false, value: 0 }")
        stop_took(sim, time.monotonic())


JOG_X = json.dumps({"type": "command", "action": "arm_jog", "velocity": [0.05, 0, 0, 0, 0, 0]})
# A page's script jogging +x over a WebSocket at the page's rate for about a second.
SOCKET_JOG = """
(async (url, jog) => {
  const ws = new WebSocket(url);
  const opened = await new Promise((done) => {
    ws.onopen = () => done(true);
    ws.onerror = ws.onclose = () => done(false);
    setTimeout(() => done(false), 3000);
  });
  if (!opened) return false;
  for (let i = 0; i < 30; i++) {
    ws.send(JSON.stringify({ ...JSON.parse(jog), t_page_ms: performance.now() }));
    await new Promise((r) => setTimeout(r, 33));
  }
  ws.close();
  return true;
})
"""


def jog_from_page(browser: Chromium, sim: URSimProcess, ws_url: str) -> tuple[bool, float]:
    """(whether the page's socket opened, how far the simulator's TCP moved) for one attempt."""
    wait_still(sim)
    start = sim.tcp_pose()
    # the page's answer in the harness's own wait (a busy machine held a page 10 s), plus the
    # second the script jogs for
    opened = browser.evaluate(
        f"{SOCKET_JOG}({json.dumps(ws_url)}, {json.dumps(JOG_X)})", timeout_s=PAGE_WAIT_S + 1.0
    )
    time.sleep(0.3)
    return opened, float(np.linalg.norm(sim.tcp_pose()[:3] - start[:3]))


def test_neither_a_client_without_the_token_nor_a_rebinding_page_can_jog(station):
    """From outside the dashboard: a local client without the token, then chromium opening the
    page under a name that resolves to 127.0.0.1 (DNS rebinding; given even the token), jog for
    a second each; the simulator's arm stays put. The page's own origin, same script, moves it."""
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    from common.web.web_token import with_token

    rig, dashboard = station
    sim = rig.arm_sim
    port, token = dashboard.port, dashboard.token
    with watchdog_trips_named(rig):
        wait_still(sim)
        start = sim.tcp_pose()
        with (
            pytest.raises(InvalidStatus) as e,
            connect(f"ws://127.0.0.1:{port}/ws", open_timeout=2) as ws,
        ):
            for _ in range(30):
                ws.send(JOG_X)
                time.sleep(0.033)
        assert e.value.response.status_code == 401
        assert np.linalg.norm(sim.tcp_pose()[:3] - start[:3]) < 1e-4

        rules = "--host-resolver-rules=MAP evil.example 127.0.0.1"
        with Chromium(width=800, height=600, flags=(rules,)) as browser:
            browser.navigate(f"http://evil.example:{port}/?token={token}")
            shown = browser.evaluate("document.body.innerText")
            assert "is not one this page is served under" in shown, shown
            assert browser.evaluate("typeof dxp") == "undefined"  # no page, no script
            opened, moved = jog_from_page(
                browser, sim, with_token(f"ws://evil.example:{port}/ws", token)
            )
            assert not opened and moved < 1e-4, (opened, moved)

            # the control: the same script, same token, from the page's own origin moves it
            browser.navigate(dashboard.url)
            browser.wait_for("dxp.state.arm && dxp.state.arm.available", 20)
            opened, moved = jog_from_page(
                browser, sim, with_token(f"ws://127.0.0.1:{port}/ws", token)
            )
            assert opened and moved > 0.01, (opened, moved)
