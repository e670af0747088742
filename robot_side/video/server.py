"""Streams one video source to every browser that asks, over WebRTC (aiortc).

Signalling is one WebSocket per viewer: the viewer (the operator's
dashboard server, relaying its page) sends ``{"type": "offer", "sdp": ...}``
and gets ``{"type": "answer", "sdp": ..., "source": ..., "width": ...,
"height": ...}`` back; the peer connection lives as long as that WebSocket,
so a closed tab or a lost dashboard ends it. Media then flows straight from
this process to the browser (SRTP over UDP, VP8, congestion-controlled by
the browser's REMB feedback), or, with ``link_scenario``, through a
datagram relay of the link simulator per viewer (``simulated_link.py``).

The source (a ``robot_side.camera`` device) is shared through a relay: it is
connected when the first viewer's encoder asks for a frame and disconnected
when the last viewer leaves, so
nothing is captured or encoded for nobody. Each frame is converted to
``yuv420p`` once, on the capture thread, before the relay hands the same
frame object to every viewer's encoder: aiortc's VP8 encoder reformats any
other format on its own thread, and PyAV's ``reformat`` of one frame from
two threads at once crashes the process or hangs it
(docs/dashboard.md, Video). A ``yuv420p`` frame is passed through untouched.

Signalling needs the server's token (``?token=`` or ``Authorization:
Bearer``): a loopback port is open to every process of the PC, and any of
them could otherwise watch the lab. A request with an ``Origin`` (a
browser's) is refused outright: only the robot node and a dashboard server
speak to this socket, never a page. Media sockets bind only to
``media_interfaces`` (``media_binding.py``).

``stop()`` (SIGTERM, Ctrl-C) closes every viewer's peer connection and
returns within its timeout even when an encoder thread is stuck in native
code; it says whether the server stopped cleanly, so the process can exit
without waiting for such a thread.
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import contextlib
import json
import logging
import threading
import time
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

from common import bounded_json, web_token
from common.config import param
from common.errors import ConfigError
from common.ice import IceConfig
from robot_side.camera import KINDS as CAMERA_KINDS
from robot_side.camera.base import Camera, CapturedFrame, build_camera
from robot_side.camera.config import LabCameraConfig, TestPatternConfig, V4L2Config
from robot_side.video import media_binding
from robot_side.video.feed import CameraFeed
from robot_side.video.recording import CameraRecording
from robot_side.video.simulated_link import SimulatedMediaPath, scenario_for, without_candidates

log = logging.getLogger(__name__)

VIDEO_CLOCK = 90_000  # RTP's video clock rate
OFFER_TIMEOUT_S = 10.0
#: for every viewer's peer connection, then every signalling socket, to close at stop: one
#: budget for both, inside stop()'s own (a stop must end well within systemd's
#: TimeoutStopSec, the fault matrix's and the tests' bounds)
CLOSE_TIMEOUT_S = 3.0
#: for the loop's last tasks (the relay's readers, a viewer's session ending) once cancelled
CANCEL_TIMEOUT_S = 1.0
#: how long a signalling socket's close waits for the other end's close frame: a viewer
#: whose process froze or whose loop already ended never sends one, and websockets' own
#: 10 s default then held up every stop by as long (the dashboard's server waits 1 s too)
WS_CLOSE_TIMEOUT_S = 1.0
SHARED_FORMAT = "yuv420p"  # what the VP8 encoder takes as it is (no reformat on its thread)


class _Viewer:
    """One viewer's slot: whether a controller's, and how it was ended early (if it was)."""

    def __init__(self, controller: bool) -> None:
        self.controller = controller
        self.ended = asyncio.Event()
        self.why = ""  # the close reason its signalling socket gets

    def end(self, why: str) -> None:
        self.why = why
        self.ended.set()


@dataclass
class VideoConfig:
    host: str = param(
        "127.0.0.1",
        "signalling address: loopback, where the robot node carries viewers' offers "
        "(its link.video_url); another only for dashboards connecting straight here",
    )
    port: int = param(8890, "signalling WebSocket port (media uses UDP ports ICE picks)")
    token_file: Path | None = param(
        None,
        "the file holding the secret a viewer's signalling must present (created, mode 0600, "
        "when missing; the robot node's link.video_token_file names the same file); "
        "unset: a fresh secret each run, in the URL printed at start",
    )
    media_interfaces: tuple[str, ...] = param(
        ("lo",),
        "network interfaces (e.g. eth0) or addresses the media's UDP sockets bind to: the one "
        "the operators' browsers reach this PC on; lo (loopback) only by default",
    )
    source: str = param(
        "test_pattern",
        f"which camera: one of {', '.join(CAMERA_KINDS)} (lab: a simulated lab's camera)",
    )
    max_viewers: int = param(
        4,
        "peer connections at once; each costs an encoder. When all are taken, a controller's "
        "offer (the robot node says whose) closes an observer's session to make room",
    )
    ice_timeout_s: float = param(
        10.0,
        "a viewer whose connection (ICE, then DTLS) has not completed this long after its "
        "answer gives its slot back: an offer that never connects holds no slot for longer",
    )
    ice: IceConfig = param(
        IceConfig(), "STUN/TURN servers; the operator's dashboard needs the same"
    )
    link_scenario: str = param(
        "",
        "a netsim scenario (name or .toml) each viewer's media crosses, through a datagram "
        "relay of its own (deepxpalm demo --scenario sets it); empty = straight to the viewer",
    )
    link_seed: int = param(0, "the media's impairment seed (with link_scenario)")
    test_pattern: TestPatternConfig = param(TestPatternConfig(), "the stamped test picture")
    v4l2: V4L2Config = param(V4L2Config(), "a USB camera on the robot PC")
    lab: LabCameraConfig = param(LabCameraConfig(), "a camera of a running simulated lab")
    record: Path | None = param(
        None,
        "record the camera into this MCAP file for as long as the server runs (beside the "
        "robot's recording: DIR/camera.mcap; deepxpalm demo --record sets it); unset: no recording",
    )
    record_fps: float = param(
        10.0, "frames a second recorded (at most the camera's own rate); JPEG, about 15-50 kB each"
    )

    def __post_init__(self) -> None:
        if not 0.1 <= self.record_fps <= 60:
            raise ValueError(f"video record_fps must be 0.1..60, not {self.record_fps}")
        if not 0 <= self.port <= 65535:
            raise ValueError(f"video port must be 0..65535, not {self.port}")
        if self.max_viewers < 1:
            raise ValueError("video max_viewers must be at least 1")
        if not 0 < self.ice_timeout_s <= 120:
            raise ValueError(f"video ice_timeout_s must be in (0, 120], not {self.ice_timeout_s}")
        if not self.media_interfaces:
            raise ValueError("video media_interfaces must name at least one interface (e.g. lo)")


def camera_key(config: VideoConfig) -> str:
    """The camera's name in recordings and datasets (``observation.images.<key>``)."""
    return config.lab.camera if config.source == "lab" else config.source


def build_source(config: VideoConfig) -> Camera:
    """The camera ``config.source`` names, from its own section (``[video.<kind>]``)."""
    return build_camera(config.source, getattr(config, config.source, None))


def _shareable(frame: CapturedFrame) -> Any:
    """``frame`` as a ``yuv420p`` VideoFrame every viewer's encoder may share."""
    import av

    rgb = av.VideoFrame.from_ndarray(frame.rgb, format="rgb24")
    return rgb.reformat(format=SHARED_FORMAT)


def _source_track(feed: CameraFeed, thread_prefix: str) -> Any:
    """An aiortc track of ``feed``'s frames: subscribed on its first frame, until ``stop``.

    Frames are taken on a thread whose name starts with ``thread_prefix`` (the server's
    ``stop()`` waits for its threads by name)."""
    import av
    from aiortc import MediaStreamTrack
    from aiortc.mediastreams import MediaStreamError

    class SourceTrack(MediaStreamTrack):
        kind = "video"

        def __init__(self) -> None:
            super().__init__()
            self._pool = concurrent.futures.ThreadPoolExecutor(
                1, thread_name_prefix=f"{thread_prefix}-cap"
            )
            self._open = False
            self._seq = 0
            self._t0: int | None = None
            self.frames = 0

        def _next(self) -> tuple[CapturedFrame, Any]:
            # until stopped, or the feed closed (its next_frame then returns at once: no spin)
            while self.readyState == "live" and not feed.closed:
                got = feed.next_frame(self._seq, timeout_s=0.5)
                if got is not None:
                    self._seq, frame = got
                    return frame, _shareable(frame)
            raise MediaStreamError

        async def recv(self) -> av.VideoFrame:
            if self.readyState != "live":
                raise MediaStreamError  # the relay's reader ends quietly
            loop = asyncio.get_running_loop()
            if not self._open:
                feed.subscribe("viewer")
                self._open = True
            try:
                frame, out = await loop.run_in_executor(self._pool, self._next)
            except RuntimeError:  # stopped meanwhile: the pool no longer takes work
                raise MediaStreamError from None
            if self._t0 is None:
                self._t0 = frame.capture_ns
            out.pts = (frame.capture_ns - self._t0) * VIDEO_CLOCK // 1_000_000_000
            out.time_base = Fraction(1, VIDEO_CLOCK)
            self.frames += 1
            return out

        def stop(self) -> None:
            super().stop()
            if self._open:
                self._open = False
                feed.unsubscribe("viewer")
            self._pool.shutdown(wait=False)

    return SourceTrack()


def rtc_configuration(ice: IceConfig) -> Any:
    """aiortc's configuration: exactly the configured servers (none: host candidates only).

    Left unset, aiortc would ask Google's public STUN server from the robot PC.
    """
    from aiortc import RTCConfiguration, RTCIceServer

    return RTCConfiguration(iceServers=[RTCIceServer(**server) for server in ice.as_dicts()])


class VideoServer:
    """Answers WebRTC offers on a WebSocket and streams ``source``; ``start()`` / ``stop()``."""

    def __init__(self, source: Camera, config: VideoConfig | None = None) -> None:
        self.source = source
        self.config = config or VideoConfig()
        self.port = self.config.port
        self._viewers: list[_Viewer] = []  # the slots taken, oldest first (the loop's thread)
        self.sessions = 0
        self.peak_viewers = 0  # the most slots ever taken at once
        #: refusals and ends, by kind: bad_offers, offers_refused_full, viewers_preempted, ...
        self.counters: collections.Counter[str] = collections.Counter()
        self._track: Any = None
        self._relay: Any = None
        self.feed: CameraFeed | None = None
        self.recording: CameraRecording | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._thread: threading.Thread | None = None
        self._started = threading.Event()
        self._error: BaseException | None = None
        self._peers: set[Any] = set()  # the viewers' RTCPeerConnections (the loop's thread)
        #: this server's worker threads (encoders, frame taking): stop() knows them by name
        self._encoder_prefix = f"video-encode-{id(self):x}"
        if self.config.token_file is not None:
            self.token = web_token.token_file(self.config.token_file, "video token_file")
        else:
            self.token = web_token.new_token()
        #: the addresses media sockets may bind to (checked here: a wrong name fails at start)
        self.media_addresses = media_binding.addresses(self.config.media_interfaces)
        #: the scenario every viewer's media crosses (None: direct), and its outages' origin;
        #: a ``Scenario`` built in code may replace it before the first viewer
        self.link_scenario = scenario_for(self.config.link_scenario)
        self.link_start_ns: int | None = None
        #: the simulated paths of the viewers connected now
        self.media_paths: list[SimulatedMediaPath] = []

    @property
    def base_url(self) -> str:
        """The signalling address without the token: what a log line may show."""
        return f"ws://{self.config.host}:{self.port}/"

    @property
    def url(self) -> str:
        """The signalling address with the token: what a viewer connects to."""
        return web_token.with_token(self.base_url, self.token)

    def start(self, timeout_s: float = 10.0) -> VideoServer:
        # imported here, untimed: on a busy machine importing aiortc alone can take seconds,
        # which is not the server failing to bind
        try:
            import aiortc.contrib.media  # noqa: F401
            import websockets.asyncio.server  # noqa: F401
        except ImportError as e:
            raise ConfigError(
                f"video: {e.name} is not installed (pip install 'deepxpalm[video]')"
            ) from None

        self.link_start_ns = time.monotonic_ns()
        self.feed = CameraFeed(self.source)
        self._thread = threading.Thread(target=self._run, name="video-server", daemon=True)
        self._thread.start()
        if not self._started.wait(timeout_s):
            raise ConfigError(
                f"video: not serving on {self.config.host}:{self.config.port} after "
                f"{timeout_s:g} s (is the machine overloaded?)"
            )
        if self._error is not None:
            raise ConfigError(
                f"video: cannot serve on {self.config.host}:{self.config.port}: {self._error} "
                "(is another program using the port?)"
            )
        if self.config.record is not None:  # for as long as the server runs
            from common.config import config_toml

            node = {"node": "video", "config_toml": config_toml(self.config, "video")}
            self.recording = CameraRecording(
                self.feed,
                self.config.record,
                self.config.record_fps,
                camera_key(self.config),
                {"deepxpalm.node": node},
            ).start()
        log.info(
            "video signalling at %s (token-protected), source %s, media on %s",
            self.base_url,
            self.source.name,
            ", ".join(self.media_addresses),
        )
        return self

    def stop(self, timeout_s: float = 5.0) -> bool:
        """Close every viewer and stop serving; False when something did not end in time.

        Waits at most ``timeout_s``. An encoder thread stuck in native code is
        not waited for beyond that; then, and only then, the answer is False
        and the process should exit without joining its threads
        (``deepxpalm video`` does).
        """
        thread, self._thread = self._thread, None
        if thread is None:
            return True
        if self.recording is not None:
            self.recording.stop()
            self.recording = None
        deadline = time.monotonic() + timeout_s

        def left() -> float:
            return max(0.0, deadline - time.monotonic())

        if self._loop is not None and self._stop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)
        thread.join(left())
        if self.feed is not None:
            self.feed.close(left())
        stuck = [t for t in threading.enumerate() if t.name.startswith(self._encoder_prefix)]
        for t in stuck:
            t.join(left())
        stuck = [t.name for t in stuck if t.is_alive()]
        if thread.is_alive() or stuck:
            log.error(
                "video: did not stop within %.1f s (server thread %s, encoder threads %s)",
                timeout_s,
                "running" if thread.is_alive() else "ended",
                stuck or "ended",
            )
            return False
        return True

    def __enter__(self) -> VideoServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def viewers(self) -> int:
        """Viewers holding a slot now."""
        return len(self._viewers)

    def stats(self) -> dict[str, float]:
        """Counters for ``--stats-file``: sessions, the peak of slots taken, refusals."""
        out = {k: float(v) for k, v in self.counters.items()}
        out.update(sessions=float(self.sessions), peak_viewers=float(self.peak_viewers))
        return out

    @property
    def frames_encoded(self) -> int:
        """Frames taken from the source by the current track (0 while nobody watches)."""
        return 0 if self._track is None else self._track.frames

    # ------------------------------------------------------------ internals
    def _run(self) -> None:
        # The encoders run on the loop's default executor (aiortc's RTCRtpSender):
        # named, so stop() can tell whether they ended, and never joined at exit here.
        loop = asyncio.new_event_loop()
        asyncio.set_event_loop(loop)  # this thread's own
        encoders = concurrent.futures.ThreadPoolExecutor(thread_name_prefix=self._encoder_prefix)
        loop.set_default_executor(encoders)
        try:
            loop.run_until_complete(self._main())
        except BaseException as e:
            if not self._started.is_set():
                self._error = e
                self._started.set()
            else:
                log.exception("video server stopped on an error")
        finally:
            encoders.shutdown(wait=False, cancel_futures=True)
            left = asyncio.all_tasks(loop)  # the relay's readers, waiting on a capture
            for task in left:
                task.cancel()
            if left:  # bounded: stop() waits for this thread only so long
                loop.run_until_complete(asyncio.wait(left, timeout=CANCEL_TIMEOUT_S))
            loop.run_until_complete(loop.shutdown_asyncgens())
            loop.close()

    async def _main(self) -> None:
        from aiortc.contrib.media import MediaRelay
        from websockets.asyncio.server import serve

        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        self._relay = MediaRelay()
        media_binding.restrict(self.media_addresses)  # for the peer connections of this loop
        async with serve(
            self._session,
            self.config.host,
            self.config.port,
            max_size=256 * 1024,
            process_request=self._authorise,
            close_timeout=WS_CLOSE_TIMEOUT_S,
        ) as server:
            self.port = server.sockets[0].getsockname()[1]
            self._started.set()
            await self._stop.wait()
            # every viewer's peer connection closed first (the browser hears a BYE
            # rather than waiting for ICE to time out), then the signalling sockets,
            # both within CLOSE_TIMEOUT_S
            deadline = self._loop.time() + CLOSE_TIMEOUT_S
            peers = [asyncio.ensure_future(pc.close()) for pc in self._peers]
            if peers:
                _, late = await asyncio.wait(peers, timeout=CLOSE_TIMEOUT_S / 2)
                if late:
                    log.warning("video: %d viewer(s) did not close in time", len(late))
            server.close(code=1001, reason="video server stopping")
            try:
                await asyncio.wait_for(server.wait_closed(), max(0.1, deadline - self._loop.time()))
            except TimeoutError:
                log.warning("video: signalling sessions did not end in time")
        if self._track is not None:
            self._track.stop()
            self._track = None

    def _authorise(self, conn: Any, request: Any) -> Any:
        """None for a viewer holding the token; else the refusal (no socket, no stream)."""
        import http

        if request.headers.get_all("Origin"):
            log.warning("video: refused a signalling request from a browser page (Origin set)")
            return conn.respond(http.HTTPStatus.FORBIDDEN, "no browser pages here\n")
        given = [web_token.from_query(request.path), web_token.from_bearer(request.headers)]
        if any(web_token.matches(t, self.token) for t in given):
            return None
        log.warning("video: refused a signalling request without the token")
        return conn.respond(http.HTTPStatus.UNAUTHORIZED, "the video server's token is needed\n")

    async def _offer(self, conn: Any) -> tuple[str, bool] | None:
        """(sdp, a controller's?) of the first good offer; None if none came in time.

        A message that is not an offer (malformed JSON of any depth, a wrong
        field) gets an ``error`` reply naming what is wrong, and the socket
        waits for a good one until ``OFFER_TIMEOUT_S`` from its opening.
        """
        deadline = time.monotonic() + OFFER_TIMEOUT_S
        while True:
            try:
                raw = await asyncio.wait_for(conn.recv(), deadline - time.monotonic())
            except TimeoutError:
                return None
            try:
                offer = bounded_json.loads(raw)
                if not isinstance(offer, dict) or offer.get("type") != "offer":
                    raise ValueError('expected {"type": "offer", "sdp": ...}')
                sdp = offer.get("sdp")
                if not isinstance(sdp, str):
                    raise ValueError("the offer's sdp must be a string")
                # a dashboard connecting straight here holds the token: the operator's own
                return sdp, offer.get("role", "controller") == "controller"
            except ValueError as e:  # UnicodeDecodeError and bounded_json.TooDeep included
                self.counters["bad_offers"] += 1
                await conn.send(json.dumps({"type": "error", "error": f"bad offer: {e}"[:200]}))

    def _take_slot(self, controller: bool) -> _Viewer | None:
        """A viewer's slot, checked and taken in one step (no await: offers at once keep the
        bound). When every slot is taken, a controller's offer ends the oldest session of
        another role and takes its slot; None: no slot for this offer."""
        if len(self._viewers) >= self.config.max_viewers:
            victim = next((v for v in self._viewers if not v.controller), None)
            if not controller or victim is None:
                return None
            self._viewers.remove(victim)
            victim.end("closed to make room for a controller's video")
            self.counters["viewers_preempted"] += 1
        viewer = _Viewer(controller)
        self._viewers.append(viewer)
        self.sessions += 1
        self.peak_viewers = max(self.peak_viewers, len(self._viewers))
        return viewer

    async def _session(self, conn: Any) -> None:
        from websockets.exceptions import ConnectionClosed

        try:
            offer = await self._offer(conn)
        except ConnectionClosed:
            log.debug("video: a connection closed before offering (a probe, or a page gone)")
            return
        if offer is None:
            await conn.close(1008, f"no offer within {OFFER_TIMEOUT_S:.0f} s")
            return
        sdp, controller = offer
        viewer = self._take_slot(controller)
        if viewer is None:
            self.counters["offers_refused_full"] += 1
            first = "" if controller else ", and a controller's offer comes first"
            await conn.close(1013, f"at most {self.config.max_viewers} viewers{first}")
            return
        try:
            await self._serve_viewer(conn, sdp, viewer)
        except ConnectionClosed:  # the other end went away while we answered
            log.debug("video: a viewer's signalling closed during its offer")
        except Exception as e:  # one viewer's offer aiortc cannot take: that viewer told, no more
            self.counters["offers_failed"] += 1
            log.warning("video: a viewer's offer failed: %s: %s", type(e).__name__, e)
            with contextlib.suppress(ConnectionClosed):
                await conn.close(1011, f"the offer failed: {type(e).__name__}: {e}"[:120])

    async def _serve_viewer(self, conn: Any, sdp: str, viewer: _Viewer) -> None:
        """Answer ``sdp`` and hold the session; the slot is ``viewer``'s until this returns."""
        from aiortc import RTCPeerConnection, RTCSessionDescription

        pc = RTCPeerConnection(rtc_configuration(self.config.ice))
        closed = asyncio.Event()
        connected = asyncio.Event()

        @pc.on("connectionstatechange")
        async def _state() -> None:
            log.info("video: viewer %s", pc.connectionState)
            if pc.connectionState == "connected":
                connected.set()
            if pc.connectionState in ("failed", "closed"):
                closed.set()

        path: SimulatedMediaPath | None = None
        self._peers.add(pc)
        try:
            if self._track is None:
                self._track = _source_track(self.feed, self._encoder_prefix)
            pc.addTrack(self._relay.subscribe(self._track, buffered=False))
            # mDNS (.local) candidates would open a listener on 0.0.0.0:5353: dropped,
            # the browser's checks reach our candidates and ICE learns its address
            sdp = media_binding.without_mdns_candidates(sdp)
            if self.link_scenario is not None:
                sdp = without_candidates(sdp)  # reached only through the simulator
            await pc.setRemoteDescription(RTCSessionDescription(sdp=sdp, type="offer"))
            await pc.setLocalDescription(await pc.createAnswer())
            answer = pc.localDescription.sdp
            if self.link_scenario is not None:
                assert self.link_start_ns is not None
                path = SimulatedMediaPath(
                    self.link_scenario, seed=self.config.link_seed, start_ns=self.link_start_ns
                )
                self.media_paths.append(path)
                answer = path.route(answer)
            await conn.send(
                json.dumps(
                    {
                        "type": "answer",
                        "sdp": answer,
                        "source": self.source.name,
                        "width": self.source.width,
                        "height": self.source.height,
                        "fps": self.source.fps,
                    }
                )
            )
            ending = {
                asyncio.create_task(conn.wait_closed()),
                asyncio.create_task(closed.wait()),
                asyncio.create_task(viewer.ended.wait()),
            }
            up = asyncio.create_task(connected.wait())
            try:
                # half-open (ICE or DTLS not completed) for at most ice_timeout_s: its slot
                # goes back, whoever made the offer and whether or not they answer checks
                done, _ = await asyncio.wait(
                    {up, *ending},
                    timeout=self.config.ice_timeout_s,
                    return_when=asyncio.FIRST_COMPLETED,
                )
                if not done:
                    self.counters["viewers_half_open_ended"] += 1
                    viewer.end(f"ICE/DTLS did not complete within {self.config.ice_timeout_s:g} s")
                    log.info("video: a viewer's %s", viewer.why)
                elif up in done and not done & ending:
                    await asyncio.wait(ending, return_when=asyncio.FIRST_COMPLETED)
            finally:
                for task in (up, *ending):
                    task.cancel()
        finally:
            if viewer in self._viewers:
                self._viewers.remove(viewer)
            self._peers.discard(pc)
            await pc.close()
            if path is not None:
                self.media_paths.remove(path)
                await asyncio.get_running_loop().run_in_executor(None, path.stop)
            if not self._viewers and self._track is not None:
                self._track.stop()
                self._track = None
            await conn.close(1000, viewer.why[:120])
