"""The video server's viewers: each one's signalling session, slot and peer connection.

Signalling is one WebSocket per viewer: the viewer (the operator's
dashboard server, relaying its page) sends ``{"type": "offer", "sdp": ...}``
and gets ``{"type": "answer", "sdp": ..., "source": ..., "width": ...,
"height": ...}`` back; the peer connection lives as long as that WebSocket,
so a closed tab or a lost dashboard ends it. Slots are bounded
(``max_viewers``): a controller's offer may close an observer's session to
make room; a connection that does not complete within ``ice_timeout_s``
gives its slot back.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import json
import logging
import time
from typing import Any

from common.web import bounded_json
from robot_side.camera.base import Camera
from robot_side.video import media_binding
from robot_side.video.config import VideoConfig
from robot_side.video.feed import CameraFeed
from robot_side.video.simulated_link import SimulatedMediaPath, without_candidates
from robot_side.video.track import rtc_configuration, source_track

log = logging.getLogger(__name__)

OFFER_TIMEOUT_S = 10.0


class Viewer:
    """One viewer's slot: whether a controller's, and how it was ended early (if it was)."""

    def __init__(self, controller: bool) -> None:
        self.controller = controller
        self.ended = asyncio.Event()
        self.why = ""  # the close reason its signalling socket gets

    def end(self, why: str) -> None:
        self.why = why
        self.ended.set()


class ViewerSessions:
    """Every viewer's session; the shared camera track runs while one is held."""

    def __init__(self, source: Camera, config: VideoConfig, encoder_prefix: str) -> None:
        self.source = source
        self.config = config
        self.held: list[Viewer] = []  # the slots taken, oldest first (the loop's thread)
        self.sessions = 0
        self.peak_viewers = 0  # the most slots ever taken at once
        #: refusals and ends, by kind: bad_offers, offers_refused_full, viewers_preempted, ...
        self.counters: collections.Counter[str] = collections.Counter()
        self.peers: set[Any] = set()  # the viewers' RTCPeerConnections (the loop's thread)
        #: the simulated paths of the viewers connected now
        self.media_paths: list[SimulatedMediaPath] = []
        self.feed: CameraFeed | None = None
        self.link_scenario: Any = None
        self.link_start_ns: int | None = None
        self._encoder_prefix = encoder_prefix
        self._track: Any = None
        self._relay: Any = None

    def open(self, feed: CameraFeed, link_scenario: Any, link_start_ns: int) -> None:
        """The server started: the camera's feed, and the link every viewer's media crosses
        (None: direct) with its clock's origin."""
        self.feed, self.link_scenario, self.link_start_ns = feed, link_scenario, link_start_ns

    @property
    def viewers(self) -> int:
        """Viewers holding a slot now."""
        return len(self.held)

    @property
    def frames_encoded(self) -> int:
        """Frames taken from the source by the current track (0 while nobody watches)."""
        return 0 if self._track is None else self._track.frames

    async def close_peers(self, timeout_s: float) -> None:
        """Close every viewer's peer connection (the browser hears a BYE)."""
        peers = [asyncio.ensure_future(pc.close()) for pc in self.peers]
        if peers:
            _, late = await asyncio.wait(peers, timeout=timeout_s)
            if late:
                log.warning("video: %d viewer(s) did not close in time", len(late))

    def stop_track(self) -> None:
        if self._track is not None:
            self._track.stop()
            self._track = None

    async def session(self, conn: Any) -> None:
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

    def _take_slot(self, controller: bool) -> Viewer | None:
        """A viewer's slot, checked and taken in one step (no await: offers at once keep the
        bound). When every slot is taken, a controller's offer ends the oldest session of
        another role and takes its slot; None: no slot for this offer."""
        if len(self.held) >= self.config.max_viewers:
            victim = next((v for v in self.held if not v.controller), None)
            if not controller or victim is None:
                return None
            self.held.remove(victim)
            victim.end("closed to make room for a controller's video")
            self.counters["viewers_preempted"] += 1
        viewer = Viewer(controller)
        self.held.append(viewer)
        self.sessions += 1
        self.peak_viewers = max(self.peak_viewers, len(self.held))
        return viewer

    async def _serve_viewer(self, conn: Any, sdp: str, viewer: Viewer) -> None:
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
        self.peers.add(pc)
        try:
            if self._track is None:
                self._track = source_track(self.feed, self._encoder_prefix)
            if self._relay is None:
                from aiortc.contrib.media import MediaRelay

                self._relay = MediaRelay()
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
            if viewer in self.held:
                self.held.remove(viewer)
            self.peers.discard(pc)
            await pc.close()
            if path is not None:
                self.media_paths.remove(path)
                await asyncio.get_running_loop().run_in_executor(None, path.stop)
            if not self.held and self._track is not None:
                self._track.stop()
                self._track = None
            await conn.close(1000, viewer.why[:120])
