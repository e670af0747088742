"""STOP means stop: two pages of one dashboard and a gamepad, the arm read from the UR simulator.

Page A holds a jog (a key held down, as a person holds it); STOP is pressed
on page B, with the mouse and then with a gamepad's stop button. The arm,
read from the simulator (not from any node), must come to rest at once and
stay at rest while A still holds its key, both pages must show the robot's
latch, and only a RESUME lets a jog move the arm again (after A lets go
and presses again: a resume never restarts a held jog).

Before the latch lived on the robot, B's stop lasted until A's next jog,
33 ms later: the arm went on at 30 mm/s.

Times are wall-clock (``time.time()`` here, ``Date.now()`` in the pages,
the time stamps of the robot node's log lines, to the millisecond), one
clock on one machine, so a stop is timed from the press in the page, not
from when DevTools got round to delivering it. The robot node runs as its
own process, the operator node with its dashboard another and the UR
simulator a third (``running_station``).
"""

from __future__ import annotations

import statistics
import threading
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest
from headless_chromium import BrowserError, Chromium, needs_chromium
from test_arm_jog_browser import (  # noqa: F401 (station: a fixture)
    PAD,
    SPEED_SCALE,
    STILL_M_S,
    running_station,
    station,
)

from harness.bench.command_path import RobotUnderCommands
from robot_side.arm.sim import URSimProcess

pytestmark = [pytest.mark.timeout(240), pytest.mark.slow, needs_chromium]

STOP_BUDGET_MS = 100  # issue 25: a stop from any page stops a jog held on another within this
STAY_STILL_S = 1.0  # how long A holds its key against the latch
STALE_RESUMES = 2  # resumes the robot may refuse as stale (a starved machine) before it fails
#: the page reads a gamepad at its jog send rate (operator.dashboard.jog.send_rate_hz, 30 Hz)
PAD_PERIOD_MS = 1000 / 30
ROUNDS = 5  # stops of each kind: their median is held to the budget: two stalls are no verdict
JOG_M_S = SPEED_SCALE * 0.10  # the page's default speed scale times the operator's cap
KEY_W = {"key": "w", "code": "KeyW", "windowsVirtualKeyCode": 87}  # +x in the default keymap
RESUME_ACKS = "dxp.acks.filter((a) => a.action === 'arm_resume').length"
KEYUP_CLOCK = "window.addEventListener('keyup', () => (window.__keyupAt = Date.now()))"
#: the robot's own stops (logger: what it logs), which a release must not be timed by
OWN_STOPS = {"robot_side.arm.safety_threads": "(deadman)", "robot_side.node.workers": "arm stopped"}
OWN_STOP_LEAD_S = 0.1  # such a stop this long before the keyup still ends the motion after it


class SpeedLog:
    """The simulator's TCP speed every 2 ms on a thread, so a stop's timing is read off it."""

    def __init__(self, sim: URSimProcess) -> None:
        self.sim = sim
        self.samples: list[tuple[float, float, float]] = []  # (time.time(), linear, angular)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            v = self.sim.tcp_speed()
            lin, ang = float(np.linalg.norm(v[:3])), float(np.linalg.norm(v[3:]))
            self.samples.append((time.time(), lin, ang))
            time.sleep(0.002)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)

    def at_rest_after(self, t0: float, timeout_s: float = 3.0) -> float:
        """Wall time of the first sample at rest after ``t0``; fails if none in ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for t, lin, ang in list(self.samples):
                if t >= t0 and lin <= STILL_M_S and ang <= 1e-3:
                    return t
            time.sleep(0.01)
        raise AssertionError(f"the arm never came to rest within {timeout_s} s of the stop")

    def moving_at(self, t: float) -> bool:
        """Whether the newest sample at or before ``t`` has the arm at the jog's speed."""
        before = [lin for ts, lin, _ in list(self.samples) if ts <= t]
        return bool(before) and before[-1] >= 0.5 * JOG_M_S

    def top_speed(self, t0: float, t1: float) -> float:
        return max((lin for t, lin, _ in list(self.samples) if t0 <= t <= t1), default=0.0)


@pytest.fixture
def pages(station, quiet_gc) -> Iterator[tuple[Chromium, Chromium, SpeedLog]]:  # noqa: F811
    rig, dashboard = station
    with Chromium(width=1280, height=1000) as a, Chromium(width=1280, height=1000) as b:
        for page in (a, b):
            page.navigate(dashboard.url)
            page.wait_for("dxp.jog !== null && dxp.state.arm && dxp.state.arm.pose", 20)
            page.evaluate(KEYUP_CLOCK)
            # no event per WebSocket frame (90 a second here): unread, they make closing slow
            page.call("Network.disable")
        log = SpeedLog(rig.arm_sim)
        try:
            yield a, b, log
        finally:
            log.close()
        assert a.page_errors() == [] and b.page_errors() == []


def key(page: Chromium, kind: str) -> None:
    """A real key event (DevTools input), as a person presses or lets go of a key."""
    text = {"text": "w"} if kind == "keyDown" else {}
    page.call("Input.dispatchKeyEvent", type=kind, **KEY_W, **text)


def hold_until_moving(page: Chromium, log: SpeedLog, timeout_s: float = 10.0) -> None:
    """Page holds +x until the simulator's TCP runs at the jog's speed."""
    key(page, "keyDown")
    deadline = time.monotonic() + timeout_s
    while not log.samples or log.samples[-1][1] < 0.8 * JOG_M_S:
        assert time.monotonic() < deadline, (
            f"the held key never moved the arm in {timeout_s} s: {log.samples[-1:]} "
            f"(robot: {page.evaluate('JSON.stringify(dxp.state.arm)')})"
        )
        time.sleep(0.01)


def release_ms(page: Chromium, log: SpeedLog, robot: RobotUnderCommands) -> float | None:
    """Let go of the held key: ms from the page's keyup to the arm at rest (the baseline path).

    None when the arm was not moving at the keyup, or the robot stopped it on its own
    first (a loaded machine: A's jogs stalled past the deadman, 12 ms "releases" and
    rests before the keyup were seen): that times no release, as a stop with A's jog
    stalled at the press times no stop.
    """
    key(page, "keyUp")
    up = page.evaluate("window.__keyupAt") / 1000
    at_rest = log.at_rest_after(up)
    if not log.moving_at(up) or robot_stopped_on_its_own(robot, up - OWN_STOP_LEAD_S, at_rest):
        return None
    return (at_rest - up) * 1000


def robot_stopped_on_its_own(robot: RobotUnderCommands, t0: float, t1: float) -> bool:
    """Whether the arm's jog deadman or the link's deadman stopped the arm between t0 and t1."""
    return any(
        t0 <= r.created <= t1 and r.name in OWN_STOPS and OWN_STOPS[r.name] in r.message
        for r in robot.log_lines()
    )


def shows_latch(page: Chromium, latched: bool, timeout_s: float = 10.0) -> None:
    page.wait_until(
        "[dxp.latched, !document.getElementById('latch').hidden, dxp.jog.robotLatched]",
        lambda v: v == [latched] * 3,
        timeout_s=timeout_s,
    )


def stays_still_while_held(log: SpeedLog, what: str) -> None:
    t0 = time.time()
    time.sleep(STAY_STILL_S)
    top = log.top_speed(t0, time.time())
    assert top <= STILL_M_S, (
        f"the arm moved at {top * 1000:.1f} mm/s after {what} while page A held its jog: "
        "the stop did not hold"
    )


def robot_heard_stop(robot: RobotUnderCommands, after: float) -> float:
    """Wall time the robot logged the stop's arrival (it latches as it admits the command)."""
    deadline = time.monotonic() + 3
    while True:
        times = [
            r.created
            for r in robot.log_lines("robot_side.node.commands.stop_latch")
            if "latched by" in r.message
        ]
        if times and times[-1] >= after:
            return times[-1]
        assert time.monotonic() < deadline, "the robot never logged the stop"
        time.sleep(0.01)


class Stops:
    """Page A holds its key; ``press`` stops the arm; the arm, the pages and the robot are read.

    Each stop is (press, robot heard it, arm at rest) in wall seconds; each
    resume ends with a plain release of A's key, timed as the baseline.
    """

    def __init__(
        self, a: Chromium, b: Chromium, log: SpeedLog, robot: RobotUnderCommands, dashboard
    ) -> None:
        self.a, self.b, self.log, self.robot = a, b, log, robot
        self.dashboard = dashboard
        self.stops: dict[str, list[tuple[float, float, float]]] = {}
        self.releases: list[float] = []
        self.stale_resumes = 0  # resumes the robot refused as stale, each pressed again

    def stop(self, what: str, press: Callable[[], float], check_hold: bool) -> None:
        hold_until_moving(self.a, self.log)
        t0 = time.time()
        pressed = press()
        at_rest = self.log.at_rest_after(pressed)
        heard = robot_heard_stop(self.robot, t0)
        # untimed: A's jog had stuttered at the press, or the arm came to rest before the robot
        # heard the stop (a jog that stuttered after it, ended by the node's deadman): either
        # way something else stopped the arm (a loaded machine; one such read -298 ms)
        if self.log.moving_at(pressed) and at_rest >= heard:
            self.stops.setdefault(what, []).append((pressed, heard, at_rest))
        for page in (self.a, self.b):
            shows_latch(page, True)
        if check_hold:
            stays_still_while_held(self.log, what)

    def resume(self, resumer: Chromium, check_hold: bool) -> None:
        """RESUME; A's still-held key moves nothing until let go and pressed again.

        A resume is refused when it reaches the robot older than its
        ``max_command_age_ms`` (it would let the arm move on a stale wish). On
        a starved machine that happens; the page then says so and its user
        presses RESUME again, which is what this does, a few times at most.
        Any other refusal fails.
        """
        for attempt in range(1, STALE_RESUMES + 2):
            acked = resumer.evaluate(RESUME_ACKS)
            resumer.click("#arm-resume")
            try:  # the server answered this click (a click that missed the button never is)
                # 15 s: the page's renderer runs at chromium's own priority (nice 0), below the
                # nodes and the tests; beside two other deployments on two saturated cores, a
                # resume the robot had applied was not yet shown after 5 s
                resumer.wait_until(RESUME_ACKS, lambda n, acked=acked: n > acked, timeout_s=15)
            except BrowserError as e:
                raise AssertionError(
                    "the page never showed the server's answer to its click on RESUME (did the "
                    f"robot count a resume?): {self.what_each_node_counted()}"
                ) from e
            try:
                for page in (self.a, self.b):
                    shows_latch(page, False)
                break
            except BrowserError as e:  # what the page told its user about the resume
                note = resumer.evaluate("document.getElementById('latch-note').textContent")
                if "refused the resume as stale" not in note or attempt > STALE_RESUMES:
                    raise AssertionError(
                        f"the resume did not release the stop (try {attempt}); page: {note!r}; "
                        f"{self.what_each_node_counted()}"
                    ) from e
                self.stale_resumes += 1
        if check_hold:
            stays_still_while_held(self.log, "the resume (A never let go)")
        key(self.a, "keyUp")
        self.a.wait_for("!dxp.jog.latched")  # what the page says: "none (hold to move)"
        hold_until_moving(self.a, self.log)
        self.time_release()

    def time_release(self) -> None:
        """A plain release of A's held key, kept unless it timed no release (``release_ms``)."""
        took = release_ms(self.a, self.log, self.robot)
        if took is not None:
            self.releases.append(took)

    def what_each_node_counted(self) -> str:
        """The robot's command counters (its newest heartbeat) and the operator's own."""
        snap = self.dashboard.snapshot()
        robot = {k: v for k, v in snap.robot_stats.items() if k.startswith(("command", "arm_"))}
        ours = {k: v for k, v in snap.stats.items() if k.startswith(("command", "jog"))}
        return f"robot: {robot}; operator: {ours}"

    def check_budget(self, what: str, sampled_every_ms: float = 0.0) -> None:
        """Median within 100 ms of the press; over it only if the machine was slow, not the product.

        The robot's part (the stop's arrival to rest) must be within budget
        whatever the load; the whole is compared with the plain releases of a
        held key in this run, which take the same page, server, node and robot.
        """
        runs = self.stops.get(what)
        assert runs, f"load: page A's jog stuttered at every {what}; no stop could be timed"
        total = statistics.median((rest - pressed) * 1000 for pressed, _, rest in runs)
        robot = statistics.median((rest - heard) * 1000 for _, heard, rest in runs)
        release = statistics.median(self.releases) if self.releases else float("nan")
        # the releases' upper quartile: three stops against seven releases on a slow machine
        # read stops [198, 152, 41] ms against releases [123, 151, 63, 44, 52, 104, 34], one
        # spread, medians 152 and 63
        release_q3 = (
            statistics.quantiles(self.releases, n=4)[2] if len(self.releases) > 1 else release
        )
        print(
            f"{what}: arm at rest {[round((r - p) * 1000) for p, _, r in runs]} ms after the "
            f"press, {[round((r - h) * 1000) for _, h, r in runs]} ms after the robot heard it; "
            f"plain releases {[round(r) for r in self.releases]} ms"
        )
        assert robot <= STOP_BUDGET_MS, (
            f"product: the robot took {robot:.0f} ms (median) from {what}'s arrival to rest"
        )
        if total <= STOP_BUDGET_MS:
            return
        assert self.releases, f"load: the robot stopped A's jog itself at every release; {what}"
        # a key is an event; a gamepad is read every tick, which a loaded page also delays
        assert total <= 1.5 * (release_q3 + sampled_every_ms) + 20, (
            f"product: {what} took {total:.0f} ms (median) from the press to rest, budget "
            f"{STOP_BUDGET_MS}, while letting go of a held key took {release:.0f} ms (median; "
            f"upper quartile {release_q3:.0f} ms) through the same page, server and node in this "
            f"run (plus {sampled_every_ms:.0f} ms between two readings of the input): not the "
            "machine's load"
        )
        print(f"load: {what} over {STOP_BUDGET_MS} ms, and so was a plain release in this run")


def test_a_stop_on_one_page_or_a_gamepad_holds_the_jog_of_another_until_a_resume(
    station,  # noqa: F811
    pages,
):
    rig, dashboard = station  # the robot node's own log says when it heard and stopped
    a, b, log = pages
    for page in (a, b):
        shows_latch(page, False)
    run = Stops(a, b, log, rig, dashboard)
    hold_until_moving(a, log)
    run.time_release()

    def click() -> float:
        b.click("#arm-stop")
        return b.evaluate("dxp.stopSentAt") / 1000

    def pad_button() -> float:
        """The press, counted from the tick that read it less at most one polling period.

        The page reads the pad at every tick of its jog timer (30 Hz): a stop waits up to
        one period for it, which is the page's own cost. A renderer starved of the CPU runs
        that timer later still (loaded run: 199 ms from the press to rest, 18 of them the
        robot's), which is the machine's wait, as a click's is (a click is timed from the
        page's send)."""
        pressed = b.evaluate(
            "window.__pad.buttons[1] = { pressed: true, touched: true, value: 1 }; Date.now()"
        )
        b.wait_for("dxp.latched")  # pressed once: the page stops once, then it is let go
        read = max(b.evaluate("dxp.stopSentAt"), pressed)  # the tick that sent the stop
        b.evaluate("window.__pad.buttons[1] = { pressed: false, touched: false, value: 0 }")
        print(f"the page read the pad's stop {read - pressed:.0f} ms after the press")
        return (read - min(read - pressed, PAD_PERIOD_MS)) / 1000

    def rounds(what: str, press, resumer) -> None:
        """``ROUNDS`` measured stops (a few more tries on a loaded machine), each resumed."""
        for n in range(3 * ROUNDS):
            run.stop(what, press, check_hold=n == 0)
            run.resume(resumer, check_hold=n == 0)
            if len(run.stops.get(what, [])) >= ROUNDS:
                break

    # STOP ARM clicked on page B while page A holds its key; B resumes
    rounds("STOP ARM clicked on page B", click, b)
    # the gamepad's stop button (the standard mapping's B) on page B; A resumes (it may too)
    b.evaluate(PAD)
    rounds("the gamepad's stop button on page B", pad_button, a)

    # the robot's counters as its newest heartbeat reached the operator: the last resume's
    # may come a heartbeat after the pages showed the release
    deadline = time.monotonic() + 3.0
    while True:
        robot_stats = dashboard.snapshot().robot_stats
        counted = robot_stats["arm_stops_latched"] >= 2 * ROUNDS
        counted = counted and robot_stats["arm_resumes"] >= 2 * ROUNDS
        if (counted and robot_stats["arm_stop_latched"] == 0.0) or time.monotonic() > deadline:
            break
        time.sleep(0.05)
    assert robot_stats["arm_stops_latched"] >= 2 * ROUNDS, robot_stats
    assert robot_stats["arm_resumes"] >= 2 * ROUNDS, robot_stats
    assert robot_stats["arm_stop_latched"] == 0.0, robot_stats
    run.check_budget("STOP ARM clicked on page B")
    run.check_budget("the gamepad's stop button on page B", sampled_every_ms=PAD_PERIOD_MS)


def test_a_resume_the_robot_refuses_as_stale_keeps_the_stop_and_the_page_says_why(
    quiet_gc, tmp_path
):
    """A robot that finds every resume too old (1 us of max age) keeps its stop; the page says so.

    STOP is acted on however late (it only ends motion); RESUME lets the
    arm move, so it must be fresh. A person whose resume came too late is
    told to press again, not left guessing at the lease or the link.
    """
    with (
        running_station(tmp_path, max_command_age_ms=0.001) as (_, dashboard),
        Chromium(width=1280, height=1000) as page,
    ):
        page.navigate(dashboard.url)
        page.wait_for("dxp.jog !== null && dxp.state.arm && dxp.state.arm.pose", 20)
        page.click("#arm-stop")
        shows_latch(page, True)
        # from the header's right edge, where the button sits (a scrollbar coming moves both)
        where = (
            "(() => { const r = document.getElementById('arm-resume').getBoundingClientRect();"
            " return [document.documentElement.clientWidth - r.right, r.top, r.width]; })()"
        )
        before = page.evaluate(where)
        page.click("#arm-resume")
        note = page.wait_until(
            "document.getElementById('latch-note').textContent",
            lambda v: "stale" in v or "kept its stop" in v,
            timeout_s=10,
        )
        assert "refused the resume as stale" in note, note
        # the note wraps beside the button; the button stays under the pointer meanwhile
        assert page.evaluate(where) == before
        shows_latch(page, True, timeout_s=1)
        assert page.evaluate("dxp.state.arm.commands_stale") >= 1
        assert page.page_errors() == []
