"""Video sources without a browser: the time stamp survives VP8, the test pattern keeps
its pace, the V4L2 source decodes what FFmpeg gives it, and the server streams over
real WebRTC to an aiortc viewer only while one is connected."""

from __future__ import annotations

import asyncio
import json
import time
from fractions import Fraction

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

pytest.importorskip("aiortc")
import av

from robot_side.camera.config import TestPatternConfig, V4L2Config
from robot_side.camera.stamp import MS_MODULO, draw_stamp, read_stamp
from robot_side.camera.test_pattern import TestPatternCamera
from robot_side.camera.v4l2 import V4L2Camera
from robot_side.video.server import VideoConfig, VideoServer, build_source

pytestmark = [pytest.mark.slow, pytest.mark.timeout(60)]


@given(st.integers(0, MS_MODULO - 1), st.integers(0, 255), st.sampled_from([160, 320, 640, 1280]))
def test_stamp_reads_back_what_was_drawn(ms, counter, width):
    rgb = np.random.default_rng(ms % 1000).integers(0, 256, (120, width, 3), dtype=np.uint8)
    draw_stamp(rgb, ms, counter)
    assert read_stamp(rgb) == (ms, counter)


def test_stamp_survives_vp8_at_a_low_bitrate_and_garbage_is_refused():
    src = TestPatternCamera(TestPatternConfig(fps=120))
    src.connect()
    enc = av.CodecContext.create("libvpx", "w")
    enc.width, enc.height, enc.pix_fmt = 640, 480, "yuv420p"
    enc.bit_rate = 300_000
    enc.time_base = Fraction(1, 30)
    dec = av.CodecContext.create("libvpx", "r")
    sent, read = [], []
    for i in range(30):
        frame = src.capture()
        sent.append((frame.capture_ns // 1_000_000 % MS_MODULO, i))
        vf = av.VideoFrame.from_ndarray(frame.rgb, format="rgb24").reformat(format="yuv420p")
        vf.pts = i
        for packet in enc.encode(vf):
            for out in dec.decode(packet):
                read.append(read_stamp(out.to_ndarray(format="rgb24")))
    assert read and all(r is not None for r in read)
    assert read == sent[: len(read)]
    noise = np.random.default_rng(1).integers(0, 256, (480, 640, 3), dtype=np.uint8)
    assert read_stamp(noise) is None


def test_test_pattern_keeps_its_frame_rate_and_stamps_the_wall_clock():
    src = TestPatternCamera(TestPatternConfig(fps=60))
    src.connect()
    t0 = time.monotonic()
    frames = [src.capture() for _ in range(30)]
    elapsed = time.monotonic() - t0
    assert 0.45 < elapsed < 0.8
    for f in frames:
        assert f.rgb.shape == (480, 640, 3)
        assert abs(f.capture_ns - time.time_ns()) < 2e9
    assert [read_stamp(f.rgb)[1] for f in frames] == list(range(30))


def test_v4l2_source_decodes_an_ffmpeg_input(tmp_path):
    """No camera here: the same source reads a Matroska file the way it reads /dev/video0."""
    path = tmp_path / "cam.mkv"
    with av.open(str(path), "w") as out:
        stream = out.add_stream("mjpeg", rate=30)
        stream.width, stream.height, stream.pix_fmt = 320, 240, "yuvj420p"
        for i in range(10):
            rgb = np.full((240, 320, 3), 20 * i, np.uint8)
            for p in stream.encode(av.VideoFrame.from_ndarray(rgb, format="rgb24")):
                out.mux(p)
        for p in stream.encode():
            out.mux(p)
    src = V4L2Camera(V4L2Config(device=str(path), format="matroska"))
    src.connect()
    assert (src.width, src.height) == (320, 240)
    levels = [int(src.capture().rgb.mean()) for _ in range(10)]
    src.disconnect()
    assert levels == pytest.approx([20 * i for i in range(10)], abs=3)


def test_a_missing_camera_is_an_actionable_error():
    from common.errors import DeviceNotConnectedError

    with pytest.raises(DeviceNotConnectedError, match="plugged in"):
        V4L2Camera(V4L2Config(device="/dev/video-none")).connect()


async def _watch(url: str, seconds: float) -> list[int]:
    """An aiortc viewer: offer, answer, then the stamped counters of the frames received."""
    from aiortc import RTCPeerConnection, RTCSessionDescription
    from websockets.asyncio.client import connect

    pc = RTCPeerConnection()
    pc.addTransceiver("video", direction="recvonly")
    got: list[int] = []
    track_ready = asyncio.get_running_loop().create_future()
    pc.on("track", lambda t: track_ready.set_result(t))
    await pc.setLocalDescription(await pc.createOffer())
    async with connect(url) as ws:
        await ws.send(json.dumps({"type": "offer", "sdp": pc.localDescription.sdp}))
        answer = json.loads(await asyncio.wait_for(ws.recv(), 10))
        assert answer["source"] == "test_pattern" and answer["width"] == 640
        await pc.setRemoteDescription(RTCSessionDescription(answer["sdp"], "answer"))
        track = await asyncio.wait_for(track_ready, 10)
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end:
            frame = await asyncio.wait_for(track.recv(), 5)
            stamp = read_stamp(frame.to_ndarray(format="rgb24"))
            if stamp is not None:
                got.append(stamp[1])
    await pc.close()
    return got


def test_server_streams_only_while_a_viewer_is_connected():
    config = VideoConfig(port=0)
    source = build_source(config)
    with VideoServer(source, config) as server:
        time.sleep(0.3)
        # nobody watches: nothing runs
        assert source.opened == 0 and server.viewing.frames_encoded == 0
        counters = asyncio.run(_watch(server.url, 1.5))
        # it streams, in order; its rate (30 fps quiet, fewer on a starved machine, where the
        # source drops what the encoder cannot take) is measured by `deepxpalm bench --only video`
        assert len(counters) >= 10, f"{len(counters)} stamped frames in 1.5 s"
        steps = np.diff(counters) % 256
        assert np.all(steps >= 1), counters  # never a frame twice, never backwards
        deadline = time.monotonic() + 5
        while server.viewing.viewers or server.viewing.frames_encoded:
            assert time.monotonic() < deadline, "the source kept running without a viewer"
            time.sleep(0.05)
        assert source.opened == 1


# serial: beside the deployment lane's deployments (their nodes at nice -10, above it) the server
# once had not exited 10 s after the SIGTERM
@pytest.mark.serial
def test_sigterm_ends_a_server_with_two_viewers_promptly():
    """systemd's stop with viewers watching: the process exits 0 within seconds and the viewers'
    streams end. The old server's second viewer hung an encoder thread, and Python's exit waited
    for it forever: SIGTERM looked ignored."""
    import signal

    from tests_support import VideoServerProcess

    from harness.bench.video import watch

    async def watch_then_term(server) -> tuple[list, float]:
        viewers = asyncio.ensure_future(watch(server.url, 2, 30.0))
        await asyncio.sleep(4.0)
        server.proc.send_signal(signal.SIGTERM)
        t0 = time.monotonic()
        while server.proc.poll() is None and time.monotonic() - t0 < 10:
            await asyncio.sleep(0.02)
        took = time.monotonic() - t0
        return await viewers, took

    with VideoServerProcess(None, "test_pattern.width=320", "test_pattern.height=240") as server:
        runs, took = asyncio.run(watch_then_term(server))
        code = server.proc.poll()
    assert code == 0, (
        f"SIGTERM: exit {code} after {took:.1f} s; its log:\n{server.log_text()[-3000:]}"
    )
    assert took < 5.0, f"SIGTERM took {took:.1f} s"
    assert all(r.arrivals_s for r in runs), [r.summary() for r in runs]  # both were watching
    assert all(r.ended for r in runs), [r.summary() for r in runs]  # and their streams ended


def test_cameras_are_devices_whose_kinds_load_only_when_named(tmp_path):
    """The video config names a kind; only that kind's module is imported, and a V4L2 camera
    that is not there is named by the doctor's preflight before PyAV ever opens it."""
    import subprocess
    import sys

    from common.devices.lifecycle import Device
    from common.devices.preflight import FAIL, PreflightContext
    from robot_side.camera import KINDS

    probe = (
        "import sys\n"
        "from robot_side.video.server import VideoConfig, build_source\n"
        "camera = build_source(VideoConfig(source='test_pattern'))\n"
        "print(type(camera).__name__, camera.simulated,"
        " sorted(m for m in sys.modules if m.startswith('robot_side.camera.')))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, check=True, timeout=60
    ).stdout.split()
    assert out[:2] == ["TestPatternCamera", "True"]
    loaded = " ".join(out[2:])
    assert "robot_side.camera.test_pattern" in loaded
    assert "robot_side.camera.v4l2" not in loaded and "robot_side.camera.lab" not in loaded
    assert set(KINDS) == {"test_pattern", "v4l2", "lab"}

    camera = build_source(VideoConfig(source="v4l2", v4l2=V4L2Config(device="/dev/video-none")))
    assert isinstance(camera, Device) and not camera.simulated and not camera.is_connected
    assert camera.location() == "on /dev/video-none"
    findings = camera.preflight(PreflightContext(where="video.v4l2"))
    assert [f.status for f in findings] == [FAIL]
    assert "does not exist" in findings[0].detail and "video.v4l2.device" in findings[0].fix
    not_a_device = tmp_path / "video0"
    not_a_device.write_bytes(b"")
    camera = build_source(VideoConfig(source="v4l2", v4l2=V4L2Config(device=str(not_a_device))))
    assert "not a character device" in camera.preflight(PreflightContext())[0].detail

    from common.errors import ConfigError, DeviceNotConnectedError

    with pytest.raises(ConfigError, match="not one of"):
        build_source(VideoConfig(source="webcam"))
    with pytest.raises(DeviceNotConnectedError):
        TestPatternCamera().capture()  # a camera used before connect() says so
