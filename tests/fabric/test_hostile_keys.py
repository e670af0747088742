"""One key, one voice, across sites: what one member's key sends through the router disturbs
no other robot.

A real router process (QUIC, mutual TLS, its access control made from the
roster) and two real robot nodes; one controller key runs an operator process
per robot, each sending ``arm_stop`` at 20 a second. The attacker is a process
of its own (another machine), holding one legitimate member's certificate
(a robot's, an observer's): ``harness/fabric_attacks.py``. What the robots
get is judged outside the router: each robot's own count of commands and
latched stops, in the heartbeats a recorder reads through the router, in
one-second bins; the router's memory from /proc.
"""

from __future__ import annotations

import contextlib
import itertools
import signal
import threading
import time
from pathlib import Path

import pytest

from common.clocks.clock import now_ns
from common.fabric import keyexprs
from common.fabric.session import FabricConfig, cert_files, client_config, open_session
from common.wire.codec import decode_named
from common.wire.messages import Heartbeat
from harness.fabric_attacks import ROBOTS, Attacker
from harness.fleet import Fleet

#: alone: a fleet is several deployments at once (two robot PCs, the operators' PCs, the
#: router's host) and an attacker on one machine, judged per second; beside other lanes'
#: deployments the operators' loops starved (780 ms) and their STOPs came late in a burst, of
#: which the robot rightly acts on the newest: that judged the machine, not the attack
pytestmark = [pytest.mark.slow, pytest.mark.alone, pytest.mark.timeout(240)]

#: the controller's STOPs a second to each robot (the issue's rate)
COMMAND_HZ = 20.0
#: how long each attack runs while the robots' commands are counted
ATTACK_S = 3.0
#: a bin's commands may fall short of those sent in it by this share, plus one at its edges
SHORTFALL = 0.10
#: a heartbeat carries the robot's counters once a second across the fabric: a bin's count
#: is read from the first counters after its end, which may come that much later
STATS_PERIOD_S = 1.0
#: a STOP counts in a bin if it left this long before the bin's reading: the fleet's stop
#: budget across sites (test_fleet_fabric), within which a STOP is on time; a tighter lag
#: judged a loaded machine's 200 ms path as STOPs lost
LAG_NS = 400_000_000
#: the router's memory may grow this much over idle through every attack (the issue's bound)
ROUTER_GROWTH_KB = 50 * 1024
#: every this many STOPs the controller resumes instead, and the STOP it sends once a heartbeat
#: says the robot is unlatched is a press, timed from the test's hand to the robot's heartbeat
#: that shows it latched, through the router
PRESS_EVERY = 20
#: how long a resume may take to show in a heartbeat before its STOP is sent anyway (no press):
#: the STOPs not sent meanwhile go out right after, so each second keeps its count
RESUME_SHOWN_S = 0.25
#: a pressed STOP is latched within this, plus the path's delay (loopback: none), during
#: every attack: to the robot and its heartbeat back, both through the router
PRESS_BUDGET_NS = 100_000_000


def _rss_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise AssertionError(f"no VmRSS for pid {pid}")


class Wire:
    """A recorder's session: every robot heartbeat's counters, with their arrival time."""

    def __init__(self, fleet: Fleet) -> None:
        self.session = _session(fleet, "rec")
        self.stats: dict[str, list[tuple[int, dict[str, float]]]] = {r: [] for r in ROBOTS}
        #: every heartbeat's arrival and its ``arm_stop_latched`` (1.0, 0.0, None if absent)
        self.heard: dict[str, list[tuple[int, float | None]]] = {r: [] for r in ROBOTS}
        self.subs = [
            self.session.declare_subscriber(keyexprs.robot_key(r, "heartbeat"), self._on)
            for r in ROBOTS
        ]

    def _on(self, sample) -> None:
        robot, msg = decode_named(sample.payload.to_bytes())
        if isinstance(msg, Heartbeat):
            t, name = now_ns(), robot.decode()
            self.heard[name].append((t, msg.stats.get("arm_stop_latched")))
            # the whole counters (once a second), not the latch-and-ack of every heartbeat
            if "arm_stops_latched" in msg.stats or "frames_captured" in msg.stats:
                self.stats[name].append((t, msg.stats))

    def latest(self, robot: str, name: str) -> float:
        """``name`` in the newest counters of ``robot`` (0 before any)."""
        readings = list(self.stats[robot])
        return readings[-1][1].get(name, 0.0) if readings else 0.0

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.session.close()


class Stops:
    """An operator process sending ``arm_stop`` at ``COMMAND_HZ``, each send time kept; every
    ``PRESS_EVERY``-th an ``arm_resume`` instead, and the STOP after it, sent as soon as the
    robot's heartbeat says it is unlatched, is a press."""

    def __init__(self, proc, wire: Wire, robot: str) -> None:
        self.proc, self.wire, self.robot = proc, wire, robot
        self.sent: list[int] = []
        self.presses: list[tuple[int, int]] = []  # (a resume, the STOP after it) sent
        self.resumes_unseen: list[int] = []  # resumes no heartbeat showed in RESUME_SHOWN_S
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        period = 1.0 / COMMAND_HZ
        next_t = time.monotonic()
        for n in itertools.count(1):
            if self._stop.is_set():
                return
            if n % PRESS_EVERY == 0:
                self.proc.send({"action": "arm_resume"})
                resumed = now_ns()
                unlatched = self._unlatched_since(resumed)
                self.proc.send({"action": "arm_stop"})
                self.sent.append(now_ns())
                if unlatched:
                    self.presses.append((resumed, self.sent[-1]))
                else:
                    self.resumes_unseen.append(resumed)
            else:
                self.proc.send({"action": "arm_stop"})
                self.sent.append(now_ns())
            next_t += period
            self._stop.wait(max(0.0, next_t - time.monotonic()))

    def _unlatched_since(self, t_ns: int) -> bool:
        """Wait up to ``RESUME_SHOWN_S`` for a heartbeat after ``t_ns`` saying unlatched."""
        deadline = time.monotonic() + RESUME_SHOWN_S
        beats = self.wire.heard[self.robot]
        while time.monotonic() < deadline:
            if any(t >= t_ns and latched == 0.0 for t, latched in beats[-8:]):
                return True
            time.sleep(0.002)
        return False

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)


def _session(fleet: Fleet, member: str):
    fabric = FabricConfig(router_endpoint=fleet.router_endpoint, retry_ms=50.0)
    files = cert_files(fleet.cert_dir, member, "test")
    return open_session(client_config(fabric, files, "test"), f"test as {member}")


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    fleet = Fleet(
        robots=list(ROBOTS),
        operators={"c": "controller", "mallory": "observer", "rec": "recorder"},
        workdir=tmp_path_factory.mktemp("hostile"),
    )
    with fleet:
        router = fleet.start_router()
        for name in ROBOTS:
            fleet.start_robot(name, None)
        fleet.wire = Wire(fleet)
        fleet.stops = {}
        try:
            for robot in ROBOTS:
                proc = fleet.start_operator("c", robot, want_frames=False, request_control=True)
                fleet.stops[robot] = Stops(proc, fleet.wire, robot)
            fleet.wait_for(
                lambda: all(fleet.wire.latest(r, "arm_stops_latched") > 5 for r in ROBOTS),
                60,
                "both robots latching the controller's STOPs",
            )
            fleet.idle_kb = _rss_kb(router.popen.pid)
            fleet.peak_kb = fleet.idle_kb
            yield fleet
        finally:
            for s in fleet.stops.values():
                s.close()
            fleet.wire.close()
        print(f"router RSS idle {fleet.idle_kb} kB, peak {fleet.peak_kb} kB")


def _during(fleet: Fleet, attack: str, member: str, seconds: float = ATTACK_S) -> list[str]:
    """Run the attack ``attack`` with ``member``'s key, from a process of its own (an attacker
    is another machine), for ``seconds``; every robot's STOPs kept their rate in each one-second
    bin meanwhile, and the router's memory its bound. The keys the attacker heard."""
    attacker = Attacker(attack, fleet.router_endpoint, fleet.cert_dir, member).start()
    pid = fleet.procs["router"].popen.pid
    t0 = now_ns()
    try:
        while now_ns() - t0 < seconds * 1e9:
            fleet.peak_kb = max(fleet.peak_kb, _rss_kb(pid))
            time.sleep(0.05)
    finally:
        heard = attacker.end()
    t1 = now_ns()
    # the last bin's counters: every robot's first reading after the attack (one a second)
    deadline = time.monotonic() + STATS_PERIOD_S + 0.5
    while time.monotonic() < deadline and not all(
        any(t > t1 for t, _ in list(fleet.wire.stats[robot])) for robot in ROBOTS
    ):
        time.sleep(0.02)
    for robot in ROBOTS:
        sent = fleet.stops[robot].sent
        counters = list(fleet.wire.stats[robot])
        readings = [(t, c.get("arm_stops_latched", 0.0)) for t, c in counters]
        whole = dict(counters)
        # each pair of consecutive readings (a heartbeat's counters, once a second) is a bin:
        # the STOPs sent between them, less the path's delay, against those latched between
        bins = [
            (a, b)
            for a, b in itertools.pairwise(readings)
            if a[0] >= t0 and b[0] <= t1 + STATS_PERIOD_S * 1e9
        ]
        beats = sum(1 for t, _ in list(fleet.wire.heard[robot]) if t0 <= t <= t1)
        assert len(bins) >= seconds - 1, (
            f"{robot}: {len(bins)} pairs of its counters' readings in the attack; readings at"
            f" {[round((t - t0) / 1e9, 2) for t, _ in readings if t >= t0]} s after its start"
            f" (it lasted {(t1 - t0) / 1e9:.2f} s); {beats} heartbeats heard from it meanwhile"
        )
        for (ta, ca), (tb, cb) in bins:
            n_sent = sum(1 for t in list(sent) if ta - LAG_NS <= t < tb - LAG_NS)
            span_s = (tb - ta) / 1e9
            assert n_sent >= (1 - SHORTFALL) * COMMAND_HZ * span_s - 1, (
                f"the test sent only {n_sent} in {span_s:.2f} s"
            )
            moved = {
                k: v - whole[ta].get(k, 0.0)
                for k, v in whole[tb].items()
                if k.startswith(("commands_", "link_fabric_", "decode")) and v != whole[ta].get(k)
            }
            assert cb - ca >= (1 - SHORTFALL) * n_sent - 1, (
                f"{robot} latched {cb - ca:.0f} of {n_sent} STOPs in {span_s:.2f} s of the attack;"
                f" its counters meanwhile: {moved}"
            )
        _presses_latched_in_budget(fleet, robot, t0, t1)
    assert fleet.peak_kb - fleet.idle_kb < ROUTER_GROWTH_KB, (fleet.idle_kb, fleet.peak_kb)
    return heard


def _presses_latched_in_budget(fleet: Fleet, robot: str, t0: int, t1: int) -> None:
    """Every STOP pressed during the attack on a robot the resume before it had unlatched
    (its heartbeat said so) was latched, as its heartbeat says, within ``PRESS_BUDGET_NS``."""
    beats = list(fleet.wire.heard[robot])
    took: list[float] = []
    for resumed, press in [p for p in list(fleet.stops[robot].presses) if t0 <= p[1] <= t1]:
        before = [latched for t, latched in beats if resumed <= t < press and latched is not None]
        after = [t for t, latched in beats if t >= press and latched == 1.0]
        if not before or before[-1] != 0.0 or not after:
            continue  # the resume had not reached the robot yet: no press to time
        took.append((after[0] - press) / 1e6)
    print(f"{robot}: STOPs pressed during the attack latched in {[round(x) for x in took]} ms")
    unseen = [t for t in list(fleet.stops[robot].resumes_unseen) if t0 <= t <= t1]
    assert took, (
        f"{robot}: no STOP pressed on an unlatched robot during the attack: {len(unseen)}"
        f" resumes showed in no heartbeat within {RESUME_SHOWN_S} s"
    )
    assert max(took) <= PRESS_BUDGET_NS / 1e6, (
        f"{robot}: a STOP pressed during the attack latched {max(took):.0f} ms later"
        f" (budget {PRESS_BUDGET_NS / 1e6:.0f} ms): {took}"
    )


def test_a_robot_key_forging_another_robot_silences_nobody(fleet):
    reader = _session(fleet, "cell1")  # cell1's key, reading what it may not
    heard: list[str] = []
    sub = reader.declare_subscriber("dxp/cell2/op/*/*", lambda s: heard.append(str(s.key_expr)))
    try:
        _during(fleet, "forge_another_robot", "cell1")
    finally:
        sub.undeclare()
        reader.close()
    assert heard == [], heard[:5]  # cell1 read none of cell2's commands


def test_an_observer_reading_with_wildcards_gets_no_command(fleet):
    heard = _during(fleet, "read_with_wildcards", "mallory")
    assert not [k for k in heard if "/op/" in k], heard[:5]


def test_payloads_over_the_limit_floods_and_junk_from_an_observer_silence_nobody(fleet):
    _during(fleet, "flood_junk", "mallory")


def test_connection_churn_and_subscription_floods_silence_nobody(fleet):
    _during(fleet, "churn_connections", "mallory")


def test_a_restarted_router_has_every_node_back_within_2_s(fleet):
    """systemd restarts a router that died (its unit's Restart=always): robots and operators
    reconnect by themselves, and both robots latch the controller's STOPs again within 2 s
    of the router listening. Last in the module: it restarts the router."""
    fleet.stop("router", signal.SIGKILL)
    time.sleep(1.0)  # a second with no router: the robots' deadmen fire, the palms lift
    fleet.start_router()  # on the port it had: ready once it said READY=1
    t_up = now_ns()
    counts = {r: fleet.wire.latest(r, "arm_stops_latched") for r in ROBOTS}
    for robot in ROBOTS:
        fleet.wait_for(
            lambda r=robot: any(
                t > t_up and c.get("arm_stops_latched", 0) > counts[r]
                for t, c in list(fleet.wire.stats[r])
            ),
            10,
            f"{robot} latching STOPs again",
        )
        back_s = (min(t for t, _ in list(fleet.wire.heard[robot]) if t > t_up) - t_up) / 1e9
        print(f"{robot} heard again {back_s:.2f} s after the router listened")
        assert back_s <= 2.0, back_s
