"""``deepxpalm view``: a robot's link (and a session's recordings) to a Foxglove client.

The robot is a ``TelemetryPublisher`` on a bound ZeroMQ PUB; the view reads
it as ``deepxpalm topic`` does and serves it with Foxglove's own WebSocket
server. The client is written from Foxglove's WebSocket protocol, as in
tests/recording/test_foxglove_live.py: it offers the subprotocols Foxglove's
app does, reads the server's ``serverInfo`` and ``advertise`` ops, subscribes,
and decodes binary message-data frames (opcode 0x01, subscription id u32,
timestamp u64, payload); it subscribes again when the server answers
"Unknown channel ID" for a channel it has just advertised (foxglove-sdk's
race, docs/recording.md).
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import json
import re
import struct
import subprocess
import threading
import time

import numpy as np
import pytest
from deploy_support import ENV, REPO, cli
from telemetry_publisher import TelemetryPublisher
from tests_support import needs

from common.errors import ConfigError
from common.recording.foxglove import VIEW_PORT
from common.tactile.contract import SATURATION_N
from common.wire.transport import Publisher
from deploy import view_cli

pytestmark = [pytest.mark.slow, needs("foxglove"), needs("websockets")]

SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
UNKNOWN_CHANNEL = re.compile(r"Unknown channel ID: (\d+)")
#: the arm's pose the robot's heartbeats carry (m, rotation vector rad: tool down)
POSE = {"arm_x": 0.3, "arm_y": -0.1, "arm_z": 0.2, "arm_rx": 0.0, "arm_ry": np.pi, "arm_rz": 0.0}
#: what the issue asks of the view: the link's topics at a client within 5 s of its start
WITHIN_S = 5.0


def _args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    view_cli.add_arguments(parser)
    return parser.parse_args(list(argv))


@pytest.fixture
def robot(zmq_ctx):
    pub = Publisher(zmq_ctx, "tcp://127.0.0.1:*", bind=True, name=b"cell1")
    stats = {**POSE, "curve_refused": 1.0}
    with TelemetryPublisher(
        pub, {"stimulus": 30.0, "frame": 10.0, "heartbeat": 20.0}, stats=lambda: stats
    ) as telemetry:
        telemetry.endpoint = pub.endpoint
        yield telemetry
    pub.close()


@pytest.fixture
def serve():
    """Start a view (its own thread, as the command's loop); stopped and closed after."""
    started: list[tuple[view_cli.View, threading.Event, threading.Thread]] = []

    def start(*argv: str) -> view_cli.View:
        view = view_cli.View(_args(*argv))
        stop = threading.Event()
        thread = threading.Thread(target=view.run, args=(stop, 60.0), daemon=True)
        thread.start()
        started.append((view, stop, thread))
        return view

    yield start
    for view, stop, thread in started:
        stop.set()
        thread.join(10)
        view.close()


async def _watch(url: str, wanted: set[str], deadline_s: float) -> dict:
    """The ops in order, what was advertised, and the messages of ``wanted`` topics."""
    import websockets

    ops: list[str] = []
    advertised: dict[int, dict] = {}
    subs: dict[int, str] = {}
    got: dict[str, list] = {t: [] for t in wanted}
    deadline = time.monotonic() + deadline_s
    async with websockets.connect(url, subprotocols=SUBPROTOCOLS, max_size=None) as ws:
        while time.monotonic() < deadline and not all(len(v) >= 3 for v in got.values()):
            try:
                frame = await asyncio.wait_for(ws.recv(), timeout=0.5)
            except TimeoutError:
                continue
            if isinstance(frame, str):
                op = json.loads(frame)
                ops.append(op["op"])
                if op["op"] == "serverInfo":
                    ops[-1] = ("serverInfo", op.get("capabilities"))
                elif op["op"] == "advertise":
                    for ch in op["channels"]:
                        advertised[ch["id"]] = ch
                        if ch["topic"] in wanted and ch["topic"] not in subs.values():
                            subs[len(subs) + 1] = ch["topic"]
                            await _subscribe(ws, len(subs), ch["id"])
                elif op["op"] == "status" and (refused := UNKNOWN_CHANNEL.fullmatch(op["message"])):
                    channel_id = int(refused[1])
                    (sub_id,) = [s for s, t in subs.items() if t == advertised[channel_id]["topic"]]
                    await asyncio.sleep(0.05)
                    await _subscribe(ws, sub_id, channel_id)
                continue
            if frame[0] == 0x01:
                (sub_id,) = struct.unpack_from("<I", frame, 1)
                got[subs[sub_id]].append(json.loads(frame[13:]))
    return {"ops": ops, "advertised": list(advertised.values()), "got": got}


async def _subscribe(ws, sub_id: int, channel_id: int) -> None:
    message = {"op": "subscribe", "subscriptions": [{"id": sub_id, "channelId": channel_id}]}
    await ws.send(json.dumps(message))


def _pad_values(image: dict) -> np.ndarray:
    return np.frombuffer(base64.b64decode(image["data"]), "<f4")


def test_the_view_serves_the_link_to_a_foxglove_client(robot, serve):
    t_start = time.monotonic()
    view = serve("--endpoint", robot.endpoint, "--port", "0")
    wanted = {"robot/palm", "robot/tf/tcp", "robot/pads/finger_1", "robot/link"}
    seen = asyncio.run(_watch(view.url, wanted, WITHIN_S))
    took = time.monotonic() - t_start
    got = seen["got"]
    assert all(got.values()), f"nothing on {[t for t, m in got.items() if not m]} in {took:.1f} s"
    assert took < WITHIN_S + 1.0
    # the protocol: the server introduces itself first, offers nothing but watching
    assert seen["ops"][0] == ("serverInfo", [])
    types = {ch["topic"]: ch["schemaName"] for ch in seen["advertised"]}
    assert types == {
        "robot/stimulus": "deepxpalm/robot/stimulus",
        "robot/palm": "foxglove.SceneUpdate",
        "robot/pads/finger_1": "foxglove.RawImage",
        "robot/pads/finger_2": "foxglove.RawImage",
        "robot/link": "deepxpalm/robot/link",
        "robot/tf/tcp": "foxglove.FrameTransform",
    }
    tcp = got["robot/tf/tcp"][-1]
    assert (tcp["parent_frame_id"], tcp["child_frame_id"]) == ("base", "tcp")
    assert tcp["translation"] == pytest.approx({"x": 0.3, "y": -0.1, "z": 0.2})
    assert abs(tcp["rotation"]["y"]) == pytest.approx(1.0)  # tool down: pi about y
    link = got["robot/link"][-1]
    assert link["state"] == "ok" and link["curve_refused"] == 1.0
    pads = _pad_values(got["robot/pads/finger_1"][-1])
    assert pads == pytest.approx(0.5 / SATURATION_N)  # the frame's 0.5 N, as a 0..1 image
    assert {e["id"] for e in got["robot/palm"][-1]["entities"]} == {"stimulus", "contacts"}


def test_two_clients_of_one_view_and_a_second_view_each_get_the_link(robot, serve):
    """Two of everything: two Foxglove clients of one view and a client of another view of
    the same robot, all at once, each get the link's topics."""
    views = [serve("--endpoint", robot.endpoint, "--port", "0") for _ in range(2)]
    wanted = {"robot/palm", "robot/tf/tcp", "robot/link"}

    async def three() -> list[dict]:
        urls = (views[0].url, views[0].url, views[1].url)
        return await asyncio.gather(*(_watch(url, wanted, WITHIN_S) for url in urls))

    seen = asyncio.run(three())
    assert views[0].url != views[1].url
    for client, watched in zip(("first", "second", "other view's"), seen, strict=True):
        empty = [t for t, m in watched["got"].items() if not m]
        assert not empty, f"the {client} client got nothing on {empty} in {WITHIN_S} s"


def test_the_view_has_its_own_port_and_stays_on_loopback():
    from operator_side.dashboard.config import DashboardConfig

    args = _args()
    assert (args.host, args.port) == ("127.0.0.1", VIEW_PORT)
    assert DashboardConfig().port != VIEW_PORT  # one laptop tunnels to both
    with pytest.raises(ConfigError, match="allow_remote"):
        view_cli.View(_args("--host", "0.0.0.0", "--endpoint", "tcp://127.0.0.1:1"))


def test_a_session_being_recorded_is_served_beside_the_link(robot, serve, tmp_path):
    """The files give what the link has not (the arm's recorded state); a topic the link
    serves (the pads) comes from the link only, once."""
    pytest.importorskip("mcap", reason="the 'record' extra")
    from common.recording.mcap_recorder import McapRecorder

    # the recorder below flushes every 0.1 s: its messages are sent 0.3 s after their time
    view = serve(
        *("--endpoint", robot.endpoint, "--port", "0"),
        *("--follow", str(tmp_path), "--delay", "0.3"),
    )
    stop = threading.Event()

    def record() -> None:
        with McapRecorder(tmp_path / "robot.mcap", flush_interval_s=0.1, fsync=False) as rec:
            while not stop.wait(0.05):
                now = time.monotonic_ns()
                rec.write("robot/arm", now, {"tcp_pose": np.zeros(6), "joints": np.zeros(6)})
                frame = np.full((2, 10, 10), 2.0, np.float32)  # not the link's 0.5 N
                rec.write("robot/frame", now, {"frame": frame, "frame_seq": 1, "t_capture_ns": 0})

    writer = threading.Thread(target=record, daemon=True)
    writer.start()
    try:
        seen = asyncio.run(_watch(view.url, {"robot/arm", "robot/pads/finger_1"}, 15.0))
    finally:
        stop.set()
        writer.join(10)
    topics = [ch["topic"] for ch in seen["advertised"]]
    assert len(topics) == len(set(topics)), topics  # each topic once
    assert {"robot/arm", "robot/frame", "robot/pads/finger_1"} <= set(topics)
    assert seen["got"]["robot/arm"], "nothing from the recording"
    for image in seen["got"]["robot/pads/finger_1"]:  # every one from the link
        assert _pad_values(image) == pytest.approx(0.5 / SATURATION_N)


def test_the_arm_pose_is_read_under_the_robots_own_names():
    from common.live_view.server import POSE_KEYS
    from robot_side.arm.base import TELEMETRY_POSE_KEYS

    assert POSE_KEYS == TELEMETRY_POSE_KEYS


def test_the_command_serves_until_its_duration_and_says_what_it_served(robot, tmp_path):
    """``deepxpalm view`` as a user runs it: a process that prints where to connect, serves
    a client there, and ends after ``--duration`` with its counters in ``--stats-file``."""
    stats = tmp_path / "view.json"
    proc = subprocess.Popen(
        cli(
            *("view", "--endpoint", robot.endpoint, "--port", "0"),
            *("--duration", "8", "--stats-file", str(stats)),
        ),
        stdout=subprocess.PIPE,
        text=True,
        env=ENV,
        cwd=REPO,
    )
    try:
        line = proc.stdout.readline()  # the port it bound, said
        where = re.match(r"Foxglove: open (ws://127\.0\.0\.1:[1-9]\d*) ", line)
        assert where, line
        seen = asyncio.run(_watch(where[1], {"robot/link"}, WITHIN_S))
        assert seen["got"]["robot/link"], seen["ops"]
        assert proc.wait(timeout=30) == 0
    finally:
        proc.kill()
        proc.wait()
    assert json.loads(stats.read_text())["link_sent"] > 0
