"""A live view in Foxglove: ``deepxpalm record`` serves a session being recorded.

The client is written from Foxglove's WebSocket protocol (ws-protocol; it
offers the subprotocols Foxglove's app does, ``foxglove.sdk.v1`` and
``foxglove.websocket.v1``, and the SDK's server takes the first): it reads
the server's ``advertise`` ops, sends ``subscribe`` and decodes binary message-data frames (opcode
0x01, subscription id u32, timestamp u64, payload). The session is written
by a child process through ``McapRecorder``, as the robot node and the video
server write theirs: the arm at 20 Hz, the camera at 10 fps.

The client subscribes again when the server answers "Unknown channel ID" for
a channel it has advertised: foxglove-sdk sends a channel's advertisement
before it records the channel for that client, so on a loaded machine a
subscription can arrive in between and be refused (docs/recording.md).
"""

from __future__ import annotations

import asyncio
import itertools
import json
import os
import re
import struct
import subprocess
import sys
import time
import warnings
from pathlib import Path

import pytest

from common.errors import ConfigError
from common.recording.foxglove import FoxgloveLiveConfig
from deploy.units.service import Service

make_reader = pytest.importorskip("mcap.reader", reason="the 'record' extra").make_reader
websockets = pytest.importorskip("websockets", reason="the test's client uses websockets")

#: serial: the live view's pace is judged against the recorders' 1 s flush
pytestmark = pytest.mark.serial

REPO = Path(__file__).resolve().parents[2]
HERE = Path(__file__).parent
WATCH_S = 3.0
#: the recorders flush every 1 s; 2 s more lets a loaded machine flush and read late
DELAY_S = 3.0
#: what Foxglove's app offers: the SDK's name for the protocol, and ws-protocol's original
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
#: the server's answer to a subscription to a channel it does not know (yet)
UNKNOWN_CHANNEL = re.compile(r"Unknown channel ID: (\d+)")
TOPICS = {
    "camera/image": ("foxglove.CompressedImage", 10.0),
    "robot/tf/tcp": ("foxglove.FrameTransform", 20.0),
}


async def _connect(url: str):
    """The server's socket, once it listens (the process takes a moment to start)."""
    deadline = time.monotonic() + 60
    while True:
        try:
            return await websockets.connect(
                url, subprotocols=SUBPROTOCOLS, max_size=None, open_timeout=10
            )
        except OSError:
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.2)


async def _subscribe(ws, sub_id: int, channel_id: int) -> None:
    message = {"op": "subscribe", "subscriptions": [{"id": sub_id, "channelId": channel_id}]}
    await ws.send(json.dumps(message))


async def _watch(url: str, topics: set[str], seconds: float, start) -> dict:
    """Subscribe to ``topics`` once advertised; (receive time, log time, message) per topic.

    ``start()`` is called once connected: the session begins while the view is open.
    """
    got: dict[str, list] = {t: [] for t in topics}
    advertised: dict[int, dict] = {}
    subs: dict[int, str] = {}
    resubscribed: list[int] = []
    async with await _connect(url) as ws:
        start()
        assert ws.subprotocol in SUBPROTOCOLS
        t_first = None
        deadline = time.monotonic() + 60  # the first chunks land after the recorders' flush
        while time.monotonic() < deadline:
            if t_first is not None and time.monotonic() > t_first + seconds:
                break
            try:
                frame = await asyncio.wait_for(ws.recv(), timeout=1.0)
            except TimeoutError:
                continue
            if isinstance(frame, str):
                op = json.loads(frame)
                if op["op"] == "advertise":
                    for ch in op["channels"]:
                        advertised[ch["id"]] = ch
                        if ch["topic"] in topics and ch["topic"] not in subs.values():
                            sub_id = len(subs) + 1
                            subs[sub_id] = ch["topic"]
                            await _subscribe(ws, sub_id, ch["id"])
                elif op["op"] == "status" and (refused := UNKNOWN_CHANNEL.fullmatch(op["message"])):
                    # the SDK's race (module docstring): the channel was advertised, so ask again
                    channel_id = int(refused[1])
                    (sub_id,) = [s for s, t in subs.items() if t == advertised[channel_id]["topic"]]
                    resubscribed.append(channel_id)
                    await asyncio.sleep(0.05)
                    await _subscribe(ws, sub_id, channel_id)
                continue
            if frame[0] != 0x01:  # only message data
                continue
            sub_id, log_time = struct.unpack_from("<IQ", frame, 1)
            topic = subs[sub_id]
            got[topic].append((time.monotonic(), log_time, json.loads(frame[13:])))
            if t_first is None and all(got.values()):
                t_first = time.monotonic()
    return {"got": got, "advertised": advertised, "resubscribed": resubscribed}


@pytest.mark.parametrize("host", ["0.0.0.0", "192.168.1.10", "robot-pc.local"])
def test_the_live_view_stays_on_loopback_unless_allowed(host):
    """It has no authentication and serves the camera: another host needs allow_remote."""
    with pytest.raises(ConfigError, match="allow_remote"):
        FoxgloveLiveConfig(host=host)
    assert FoxgloveLiveConfig(host=host, allow_remote=True).host == host
    for ok in ("127.0.0.1", "127.0.0.2", "localhost", "::1"):
        assert FoxgloveLiveConfig(host=ok).host == ok


def test_the_live_view_without_its_extra_says_how_to_install_it(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "foxglove", None)  # as if not installed
    from common.live_view.session_files import LiveSource

    with pytest.raises(ConfigError, match=r"pip install '\.\[foxglove\]'"):
        LiveSource(FoxgloveLiveConfig(enabled=True, follow=tmp_path))


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    pytest.importorskip("foxglove", reason="the live view needs the 'foxglove' extra")
    session = tmp_path_factory.mktemp("live")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), str(REPO / "tests")])}
    server = Service(
        "recorder",
        [
            *("record", "--duration", "90"),
            *("--set", "foxglove.enabled=true", "--set", "foxglove.port=0"),
            *("--set", f'foxglove.follow="{session}"', "--set", f"foxglove.delay_s={DELAY_S}"),
        ],
        session.parent / "recorder.log",
        env=env,
        watchdog=False,
    )
    url = server.up(60).endpoints["foxglove"]  # the port it bound, said in its READY=1
    procs = [server.popen]

    def start_writer() -> None:
        writer = subprocess.Popen(
            [sys.executable, str(HERE / "record_live_session.py"), str(session), "12"],
            env=env,
            stdout=subprocess.PIPE,
            text=True,
        )
        procs.append(writer)
        assert writer.stdout.readline().strip() == "recording"

    try:
        seen = asyncio.run(_watch(url, set(TOPICS), WATCH_S, start_writer))
        if seen["resubscribed"]:
            warnings.warn(
                f"the server refused a subscription to channel(s) {seen['resubscribed']} it had "
                "just advertised (foxglove-sdk's race); subscribed again",
                stacklevel=1,
            )
        assert procs[1].wait(timeout=60) == 0
        recorded: dict[str, list[int]] = {t: [] for t in TOPICS}
        for name in ("robot", "camera"):
            with open(session / f"{name}.mcap", "rb") as f:
                for _, channel, message in make_reader(f).iter_messages():
                    if channel.topic in recorded:
                        recorded[channel.topic].append(message.log_time)
        yield {**seen, "recorded": recorded}
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        server.close()


@pytest.mark.slow
@pytest.mark.untimed
def test_the_live_view_advertises_foxglove_types(live):
    by_topic = {ch["topic"]: ch for ch in live["advertised"].values()}
    for topic, (type_name, _) in TOPICS.items():
        ch = by_topic[topic]
        assert ch["schemaName"] == type_name and ch["encoding"] == "json"
        assert ch["schemaEncoding"] == "jsonschema"
    # the rest of the session too: the gripper's fingers, the nodes' own channels
    assert {"robot/arm", "robot/tf/finger_1", "robot/tf/finger_2"} <= set(by_topic)


@pytest.mark.slow
@pytest.mark.parametrize("topic", sorted(TOPICS))
def test_camera_and_pose_arrive_at_their_rates(live, topic):
    _, rate_hz = TOPICS[topic]
    msgs = live["got"][topic]
    assert msgs, f"no {topic} message in {WATCH_S} s"
    recv = [m[0] for m in msgs]
    stamps = [m[1] for m in msgs]
    # every message recorded in the window, once and in order, with its recorded time
    recorded = live["recorded"][topic]
    assert stamps == [t for t in recorded if stamps[0] <= t <= stamps[-1]]
    assert len(msgs) >= WATCH_S * rate_hz / 2, f"{len(msgs)} in {WATCH_S} s"
    # and sent paced, not in a burst per recorder flush (1 s): the messages of the window
    # arrived spread over it, none of its seconds without one
    span_recv = recv[-1] - recv[0]
    assert span_recv > WATCH_S - 1.0, f"{len(msgs)} messages arrived within {span_recv:.2f} s"
    gaps = [b - a for a, b in itertools.pairwise(recv)]
    assert max(gaps) < 1.0, f"a {max(gaps):.2f} s gap: sent as the recorders flush (1 s)"
    last = msgs[-1][2]
    if topic == "camera/image":
        assert last["format"] == "jpeg" and last["frame_id"] == "overview"
        assert set(last["timestamp"]) == {"sec", "nsec"}
    else:
        assert last["parent_frame_id"] == "base" and last["child_frame_id"] == "tcp"
        assert last["rotation"]["x"] == pytest.approx(0.0, abs=1e-12)
        assert abs(last["rotation"]["y"]) == pytest.approx(1.0)  # tool down: pi about y
