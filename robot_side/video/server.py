"""Streams one video source to every browser that asks, over WebRTC (aiortc).

Signalling is one WebSocket per viewer (``viewers``: its offer, slot and
peer connection); the peer connection lives as long as that WebSocket, so a
closed tab or a lost dashboard ends it. Media then flows straight from
this process to the browser (SRTP over UDP, VP8, congestion-controlled by
the browser's REMB feedback), or, with ``link_scenario``, through a
datagram relay of the link simulator per viewer (``simulated_link.py``).

The source (a ``robot_side.camera`` device) is shared through a relay: it is
connected when the first viewer's encoder asks for a frame and disconnected
when the last viewer leaves, so
nothing is captured or encoded for nobody; each frame is converted once
for every viewer's encoder (``track``).

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
import concurrent.futures
import logging
import threading
import time
from typing import Any

from common.errors import ConfigError
from common.web import web_token
from robot_side.camera.base import Camera
from robot_side.video import media_binding
from robot_side.video.camera_recording import CameraRecording
from robot_side.video.config import VideoConfig, build_source, camera_key
from robot_side.video.feed import CameraFeed
from robot_side.video.simulated_link import scenario_for
from robot_side.video.track import rtc_configuration
from robot_side.video.viewers import ViewerSessions

__all__ = [
    "VideoConfig",
    "VideoServer",
    "build_source",
    "camera_key",
    "rtc_configuration",
]

log = logging.getLogger(__name__)

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


class VideoServer:
    """Answers WebRTC offers on a WebSocket and streams ``source``; ``start()`` / ``stop()``."""

    def __init__(self, source: Camera, config: VideoConfig | None = None) -> None:
        self.source = source
        self.config = config or VideoConfig()
        self.port = self.config.port
        self.feed: CameraFeed | None = None
        self.recording: CameraRecording | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._thread: threading.Thread | None = None
        self._started = threading.Event()
        self._error: BaseException | None = None
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
        #: every viewer's signalling session, slot and peer connection
        self.viewing = ViewerSessions(self.source, self.config, self._encoder_prefix)

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
        self.viewing.open(self.feed, self.link_scenario, self.link_start_ns)
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
            from common.config.typed import config_toml

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

    def stats(self) -> dict[str, float]:
        """Counters for ``--stats-file``: sessions, the peak of slots taken, refusals."""
        viewing = self.viewing
        out = {k: float(v) for k, v in viewing.counters.items()}
        out.update(sessions=float(viewing.sessions), peak_viewers=float(viewing.peak_viewers))
        return out

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
        from websockets.asyncio.server import serve

        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        media_binding.restrict(self.media_addresses)  # for the peer connections of this loop
        async with serve(
            self.viewing.session,
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
            await self.viewing.close_peers(CLOSE_TIMEOUT_S / 2)
            server.close(code=1001, reason="video server stopping")
            try:
                await asyncio.wait_for(server.wait_closed(), max(0.1, deadline - self._loop.time()))
            except TimeoutError:
                log.warning("video: signalling sessions did not end in time")
        self.viewing.stop_track()

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
