"""Video is a controller's: an observer's offers, floods and half-open sessions never keep the
controller's page from its video; offers at once never pass the cap; deep JSON is an error.

One deployment for the module, every part its own process: a Zenoh router, a robot node on
the fabric with its video server (the stamped test pattern, ``ice_timeout_s`` 3 s), and the
controller's operator node with its dashboard. The attackers are this process, each with
its own real keys and certificate from the roster: signed video signals put through the
router, the robot's replies read from it, and the video server's signalling socket with its
token (what the robot node's bridge holds). The router's roster lets ``peek`` and ``rec``
put video offers (a compromised router): the robot's own roster still refuses them. The
controller's page is aiortc speaking the page's protocol to the dashboard, as a browser
does (tests/video_page.py).

The observers' offers name a UDP port on loopback that never answers: ICE never completes,
as with an attacker who offers and walks away. ``obs1`` and ``obs2`` are observers the
roster grants video (``video = true``), so their sessions take slots; ``peek`` is an
observer without it, ``rec`` a recorder.

The flood lasts 10 s (``FLOOD_S``) at 50 offers a second; the controller's page opens a
session every ``PAGE_EVERY_S`` while it runs, and each must play within 2 s.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
import signal
import socket
import threading
import time
from dataclasses import dataclass

import pytest

pytest.importorskip("aiortc")

from test_link_signalling import _offer_sdp
from video_page import watch_video
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

from common.clocks.clock import now_ns
from common.fabric import keyexprs
from common.fabric.link import FabricPublisher, FabricSubscriber
from common.fabric.session import FabricConfig, cert_files, client_config, open_session
from common.web.web_token import from_query, with_token
from common.wire.messages import Heartbeat, VideoSignal, new_run
from common.wire.signing import load_signer
from harness.fleet import Fleet

#: serial: the video server runs at its unit's priority (Nice=0, below the nodes' -10, as video
#: yields to control on a robot PC), and in the deployment lane other tests' nodes outranked
#: it: in four of eight clean-clone runs one page session late in the flood got its first frame
#: after 2.3 to 3.6 s, against 2, while alone or beside three lane files it took at most 0.8 s
pytestmark = [pytest.mark.slow, pytest.mark.timeout(120), pytest.mark.serial]

ICE_S = 3.0  # the video server's ice_timeout_s here (its default: 10 s)
MAX_VIEWERS = 4  # the video server's and the robot's default
#: the controller's page gets video: the answer and its first decoded frame within this
#: (one frame: aiortc's receiver here sometimes waits ~10 s for the second, attack or not)
GETS_VIDEO_S = 2.0
FLOOD_S = 10.0
FLOOD_HZ = 50.0
PAGE_EVERY_S = 1.0
ROBOT = b"cell1"


def _silent_offer(port: int) -> str:
    """A real offer whose only candidate is ``port`` on loopback, where nothing answers."""
    lines = [ln for ln in _offer_sdp().split("\r\n") if ln and not ln.startswith("a=candidate")]
    lines = [ln for ln in lines if ln != "a=end-of-candidates"]
    at = next(i for i, ln in enumerate(lines) if ln.startswith("a=ice-ufrag")) + 1
    lines[at:at] = [
        f"a=candidate:1 1 udp 2130706431 127.0.0.1 {port} typ host",
        "a=end-of-candidates",
    ]
    return "\r\n".join(lines) + "\r\n"


class SignedViewer:
    """One roster member's key: signed video signals through the router, the robot's read
    back."""

    def __init__(self, fleet: Fleet, name: str) -> None:
        signer = load_signer(fleet.members[name].signing_secret)
        files = cert_files(fleet.cert_dir, name, name)
        fabric = FabricConfig(router_endpoint=fleet.router_endpoint)
        self.session = open_session(client_config(fabric, files, name), name)
        self.pub = FabricPublisher(self.session, robot=ROBOT, operator=name, signer=signer)
        keys = tuple(keyexprs.robot_key(ROBOT, k) for k in ("video", "heartbeat"))
        self.sub = FabricSubscriber(self.session, keys, expect_name=ROBOT, latest_value=False)
        self.seq = 0
        self.run = new_run()  # this viewer's run, as a node's
        self.robot_run: int | None = None  # the robot's, echoed: the robot's replay window
        self.heard: dict[int, list[tuple[float, VideoSignal]]] = {}  # viewer -> signals

    def send(self, kind: str, viewer: int, sdp: str | None = None) -> float:
        deadline = time.monotonic() + 10.0
        while self.robot_run is None:  # a node hears the robot's run before it signals
            assert time.monotonic() < deadline, "no heartbeat from the robot"
            self.read()
            self.sub.poll(0.02)
        self.seq += 1
        self.pub.send(
            VideoSignal(
                seq=self.seq,
                t_send_ns=now_ns(),
                kind=kind,
                viewer=viewer,
                sdp=sdp,
                session=self.run,
                echo_session=self.robot_run,
            )
        )
        return time.monotonic()

    def read(self) -> None:
        for msg, _ in self.sub.drain():
            if isinstance(msg, Heartbeat) and msg.session is not None:
                self.robot_run = msg.session
            if isinstance(msg, VideoSignal):
                self.heard.setdefault(msg.viewer, []).append((time.monotonic(), msg))

    def wait(self, viewer: int, kind: str, timeout_s: float) -> tuple[float, VideoSignal]:
        """(when, the signal) of the robot's first ``kind`` for ``viewer``; fails at timeout."""
        deadline = time.monotonic() + timeout_s
        while True:
            self.read()
            for t, msg in self.heard.get(viewer, []):
                if msg.kind == kind:
                    return t, msg
            seen = [m.kind for _, m in self.heard.get(viewer, [])]
            assert time.monotonic() < deadline, f"no {kind} for viewer {viewer}: {seen}"
            self.sub.poll(0.02)

    def close(self) -> None:
        self.pub.close()
        self.sub.close()
        self.session.close()


@dataclass
class Deployment:
    fleet: Fleet
    video_url: str  # the video server's signalling URL, token included
    page_ws: str  # the controller's dashboard page socket, token included
    viewers: dict[str, SignedViewer]
    silent: str  # an offer whose ICE never completes


@pytest.fixture(scope="module")
def deployment(tmp_path_factory):
    operators = {
        "ctl": "controller",
        "obs1": "observer",
        "obs2": "observer",
        "peek": "observer",
        "rec": "recorder",
    }
    fleet = Fleet(
        robots=["cell1"],
        operators=operators,
        workdir=tmp_path_factory.mktemp("video-privilege"),
        video_observers=frozenset({"obs1", "obs2"}),
        # a compromised router: it lets peek and rec offer, the robot's roster does not
        router_roles={**operators, "peek": "controller", "rec": "controller"},
    )
    silent = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    silent.bind(("127.0.0.1", 0))  # held open and never read: checks go unanswered
    viewers: dict[str, SignedViewer] = {}
    try:
        with fleet:
            try:
                fleet.start_router()
                _, video_url = fleet.start_video(settings=(f"ice_timeout_s={ICE_S}",))  # serving
                fleet.start_robot("cell1", None, video_url=video_url)
                dashboard = ["--set", "operator.dashboard.enabled=true"]
                dashboard += ["--set", "operator.dashboard.port=0"]  # a free one, said when ready
                dashboard += ["--set", 'operator.dashboard.video_url="link"']
                ctl = fleet.start_operator("ctl", "cell1", want_frames=False, extra=dashboard)
                page = ctl.wait_ready(30).endpoints["dashboard"]
                page_port = int(page.rstrip("/").rpartition(":")[2])
                token = from_query(re.search(r"dashboard: (\S+)", ctl.log_text())[1])
                page_ws = with_token(f"ws://127.0.0.1:{page_port}/ws", token)
                for name in ("obs1", "obs2", "peek", "rec"):
                    viewers[name] = SignedViewer(fleet, name)
                time.sleep(1.0)  # the subscriptions reach the router
                yield Deployment(
                    fleet, video_url, page_ws, viewers, _silent_offer(silent.getsockname()[1])
                )
            finally:
                # while the router still answers: a Zenoh session whose router is gone waits
                # out its links' goodbye (10 s) before it closes
                for v in viewers.values():
                    v.close()
    finally:
        silent.close()


_next_viewer = iter(range(1000, 10**9))


def test_only_a_controller_or_an_observer_the_roster_grants_gets_an_answer(deployment):
    d = deployment
    refused = {}
    for name in ("peek", "rec"):
        viewer = next(_next_viewer)
        d.viewers[name].send("offer", viewer, d.silent)
        refused[name] = d.viewers[name].wait(viewer, "closed", 10)[1].reason
    assert "video is for controllers" in refused["peek"], refused
    assert "video = true" in refused["peek"], refused
    assert "recorders never get video" in refused["rec"], refused
    viewer = next(_next_viewer)
    d.viewers["obs1"].send("offer", viewer, d.silent)
    answer = d.viewers["obs1"].wait(viewer, "answer", 10)[1]
    assert "m=video" in answer.sdp
    d.viewers["obs1"].send("bye", viewer)


def test_nested_json_is_an_error_reply_and_the_socket_stays_usable(deployment):
    deep = "[" * 30_000 + "]" * 30_000

    async def page() -> tuple[list[dict], dict]:
        async with connect(deployment.page_ws, max_size=2**22) as ws:
            await ws.send('{"type": "video_offer", "sdp": ' + deep + "}")
            await ws.send(deep)
            replies = [await _next_of(ws, "ack") for _ in range(2)]
            await ws.send(json.dumps({"type": "hello"}))  # the same socket answers on
            return replies, await _next_of(ws, "ack")

    async def video() -> tuple[dict, dict]:
        async with connect(deployment.video_url, max_size=2**22) as ws:
            await ws.send(deep[:200_000])
            error = json.loads(await asyncio.wait_for(ws.recv(), 10))
            await ws.send(json.dumps({"type": "offer", "sdp": deployment.silent}))
            return error, json.loads(await asyncio.wait_for(ws.recv(), 10))

    replies, after = asyncio.run(page())
    assert all(not r["ok"] and "nested more than 32 levels" in r["error"] for r in replies)
    assert after == {"type": "ack", "ok": False, "error": "expected a command"}, after
    error, answer = asyncio.run(video())
    assert error["type"] == "error" and "nested more than 32 levels" in error["error"], error
    assert answer["type"] == "answer" and "m=video" in answer["sdp"], answer


async def _next_of(ws, kind: str) -> dict:
    while True:
        msg = json.loads(await asyncio.wait_for(ws.recv(), 10))
        if msg.get("type") == kind:
            return msg


def test_an_observers_offers_and_flood_leave_the_controllers_page_its_video(deployment):
    d = deployment
    obs1, obs2 = d.viewers["obs1"], d.viewers["obs2"]
    # 8 offers that never connect, from the two observers the roster grants video, each key's
    # offer budget full (an earlier test's offer spent some): 2 answered and 2 refused a key
    time.sleep(1.0)
    first = [(v, next(_next_viewer)) for v in (obs1, obs2) for _ in range(4)]
    for v, viewer in first:
        v.send("offer", viewer, d.silent)

    def settled() -> list[str]:
        """Each offer's first answer or refusal so far (a busy machine answers late)."""
        for v in (obs1, obs2):
            v.read()
        kinds = [[m.kind for _, m in v.heard.get(i, [])] for v, i in first]
        return [next((k for k in ks if k in ("answer", "closed")), "") for ks in kinds]

    deadline = time.monotonic() + 10.0
    while not all(settled()):
        assert time.monotonic() < deadline, f"the observers' offers unanswered: {settled()}"
        time.sleep(0.02)
    # every slot is an observer's half-open session when the controller's page first asks
    assert settled().count("answer") == MAX_VIEWERS, settled()
    stop = threading.Event()
    flood_ids: list[int] = []

    def flood() -> None:
        while not stop.is_set():
            viewer = next(_next_viewer)
            flood_ids.append(viewer)
            obs1.send("offer", viewer, d.silent)
            time.sleep(1 / FLOOD_HZ)

    flooder = threading.Thread(target=flood)
    flooder.start()
    sessions = []
    try:
        # the page opens a session every PAGE_EVERY_S while the flood runs (a page that
        # reconnects does so every few seconds: its own offers stay within its key's rate)
        t0 = time.monotonic()
        while time.monotonic() < t0 + FLOOD_S or len(sessions) < 2:
            time.sleep(max(0.0, t0 + PAGE_EVERY_S * len(sessions) + 0.3 - time.monotonic()))
            sessions.append(asyncio.run(watch_video(d.page_ws, frames=1)))
    finally:
        stop.set()
        flooder.join()
    for v in (obs1, obs2):
        v.read()
    assert all("closed" not in s for s in sessions), [s.get("closed") for s in sessions]
    slow = [(s["answer_s"], s["first_frame_s"]) for s in sessions]
    assert all(max(times) <= GETS_VIDEO_S for times in slow), f"answer, first frame (s): {slow}"
    assert len(sessions) >= 2, slow
    # the flood was refused with the reason, on the observer's own viewers
    told = [
        m.reason
        for viewer in flood_ids
        for _, m in obs1.heard.get(viewer, [])
        if m.kind == "closed" and "too many video offers" in (m.reason or "")
    ]
    assert len(told) >= FLOOD_S * 2, f"{len(told)} refusals told of {len(flood_ids)} offers"
    # and an observer's session made room for the controller's
    reasons = [
        m.reason for v in (obs1, obs2) for heard in v.heard.values() for _, m in heard
        if m.kind == "closed"
    ]  # fmt: skip
    assert any("make room for a controller" in (r or "") for r in reasons), set(reasons)
    print(f"controller's page during the flood, (answer, first frame) s: {slow}")
    for name in ("video", "cell1"):
        assert "Traceback" not in d.fleet.procs[name].log_text(), name


def test_offers_at_once_never_take_more_than_the_slots(deployment):
    async def one() -> str:
        async with connect(deployment.video_url, max_size=2**22) as ws:
            try:
                await ws.send(json.dumps({"type": "offer", "sdp": deployment.silent}))
                reply = json.loads(await asyncio.wait_for(ws.recv(), 15))
            except ConnectionClosed as e:
                return f"closed: {e.rcvd.reason if e.rcvd else e}"
            await asyncio.sleep(1.0)  # held while the others are answered
            return reply["type"]

    async def many() -> list[str]:
        return await asyncio.gather(*(one() for _ in range(12)))

    outcomes = asyncio.run(many())
    answers = outcomes.count("answer")
    assert 1 <= answers <= MAX_VIEWERS, outcomes
    refused = [o for o in outcomes if o != "answer"]
    assert all(f"at most {MAX_VIEWERS} viewers" in o for o in refused), outcomes


def test_a_half_open_session_gives_its_slot_back_after_the_ice_bound(deployment):
    """Observers' offers (as the robot's bridge marks them) fill the slots left; the next is
    refused; each answered one ends, with the reason, within the ICE bound; then a new one
    is answered again."""

    async def run() -> tuple[list[tuple[float, float, str]], str, str]:
        held, refusal = [], None
        async with contextlib.AsyncExitStack() as stack:
            for _ in range(MAX_VIEWERS + 1):
                ws = await stack.enter_async_context(connect(deployment.video_url))
                await ws.send(
                    json.dumps({"type": "offer", "sdp": deployment.silent, "role": "observer"})
                )
                try:
                    json.loads(await asyncio.wait_for(ws.recv(), 15))
                except ConnectionClosed as e:
                    refusal = e.rcvd.reason
                    break
                held.append((ws, time.monotonic()))
            assert refusal is not None, "every offer was answered: the slots have no bound"
            ends = []
            for ws, t_answer in held:
                try:
                    await asyncio.wait_for(ws.wait_closed(), ICE_S + 5)
                finally:
                    ends.append((t_answer, time.monotonic(), ws.close_reason))
        async with connect(deployment.video_url) as ws:
            await ws.send(
                json.dumps({"type": "offer", "sdp": deployment.silent, "role": "observer"})
            )
            again = json.loads(await asyncio.wait_for(ws.recv(), 15))["type"]
        return ends, refusal, again

    ends, refusal, again = asyncio.run(run())
    assert "at most 4 viewers" in refusal, refusal
    held_s = [round(end - answered, 2) for answered, end, _ in ends]
    assert all(ICE_S - 0.5 <= s <= ICE_S + 2.0 for s in held_s), held_s
    assert all("did not complete within 3 s" in reason for _, _, reason in ends), ends
    assert again == "answer"


def test_the_refusals_are_counted_and_no_log_holds_a_traceback(deployment):
    fleet = deployment.fleet
    for name in ("ctl@cell1", "cell1", "video"):
        assert fleet.stop(name, signal.SIGTERM) == 0, fleet.procs[name].log_text()[-3000:]
    robot, video = fleet.procs["cell1"].stats(), fleet.procs["video"].stats()
    assert robot.get("video_offers_refused_role", 0) >= 2, robot
    assert robot.get("video_offers_refused_rate", 0) >= FLOOD_S * FLOOD_HZ / 2, robot
    assert robot.get("video_sessions_preempted", 0) >= 1, robot
    assert video.get("peak_viewers") == MAX_VIEWERS, video
    assert video.get("viewers_half_open_ended", 0) >= MAX_VIEWERS, video
    assert video.get("bad_offers", 0) >= 1, video
    for name, proc in fleet.procs.items():
        assert "Traceback" not in proc.log_text(), f"{name}: {proc.log_text()[-3000:]}"
