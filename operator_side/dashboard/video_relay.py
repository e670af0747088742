"""A page's video, relayed: to the robot's video server, or as signals on the node's link.

The page's WebRTC offer goes to the robot's video server over a WebSocket
(``video_url`` a ``ws://`` address) or, with ``video_url = "link"``, as a
signed ``VideoSignal`` on the operator node's link, and the answer comes
back to the page; the session lasts until the page leaves or renegotiates.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import secrets
from typing import Any

from websockets.asyncio.server import ServerConnection
from websockets.exceptions import ConnectionClosed, InvalidStatus

from common.web import bounded_json, web_token
from common.wire.messages import MAX_SDP_CHARS, VideoSignal
from operator_side.dashboard.config import VIDEO_OVER_LINK, DashboardConfig
from operator_side.dashboard.web import WebServer

log = logging.getLogger(__name__)

VIDEO_ANSWER_TIMEOUT_S = 10.0
#: how long a page's video session may take to close its socket to the video server
VIDEO_CLOSE_WAIT_S = 1.0


def is_video_offer(raw: str | bytes) -> bool:
    try:
        msg = bounded_json.loads(raw)
    except ValueError:  # too deep, not UTF-8 or not JSON: the page's commands say which
        return False
    return isinstance(msg, dict) and msg.get("type") == "video_offer"


class VideoRelay:
    """The pages' video sessions; over the link, by their random viewer numbers."""

    def __init__(self, node: Any, config: DashboardConfig, server: WebServer) -> None:
        self.node = node
        self.config = config
        self.server = server
        #: video sessions over the link awaiting the robot's word, by viewer number
        self._viewers: dict[int, asyncio.Queue[VideoSignal]] = {}

    def on_video_signal(self, msg: VideoSignal) -> None:
        """On the node's thread: a robot's answer (or close) to the session awaiting it."""
        waiting = self._viewers.get(msg.viewer)
        if waiting is not None:
            self.server.call(waiting.put_nowait, msg)

    async def relay(self, conn: ServerConnection, offer: dict[str, Any]) -> None:
        if self.config.video_url == VIDEO_OVER_LINK:
            await self.over_link(conn, offer)
        else:
            await self.over_websocket(conn, offer)

    async def over_link(self, conn: ServerConnection, offer: dict[str, Any]) -> None:
        """The page's offer to the robot as a signed ``VideoSignal`` on the node's link.

        The robot's answer comes back on its telemetry, picked out by this
        session's random viewer number. The session holds until the page
        leaves or renegotiates (a ``bye`` then) or the robot closes it.
        """
        sdp = offer.get("sdp")
        if not isinstance(sdp, str) or len(sdp) > MAX_SDP_CHARS:
            reason = f"the page's offer is not a session description of <= {MAX_SDP_CHARS} chars"
            with contextlib.suppress(ConnectionClosed):
                await conn.send(json.dumps({"type": "video_closed", "reason": reason}))
            return
        viewer = secrets.randbits(63) or 1
        answers: asyncio.Queue[VideoSignal] = asyncio.Queue()
        self._viewers[viewer] = answers
        closed_by_robot = False
        try:
            self.node.send_video_signal("offer", viewer, sdp)
            try:
                msg = await asyncio.wait_for(answers.get(), VIDEO_ANSWER_TIMEOUT_S)
            except TimeoutError:
                reason = (
                    f"the robot did not answer the video offer in {VIDEO_ANSWER_TIMEOUT_S:.0f} s "
                    "(is the link up, and the robot's link.video_url set?)"
                )
            else:
                if msg.kind == "answer":
                    answer = {
                        "type": "video_answer",
                        "sdp": msg.sdp,
                        "source": msg.source,
                        "width": msg.width,
                        "height": msg.height,
                        "fps": msg.fps,
                    }
                    await conn.send(json.dumps(answer))
                    while msg.kind != "closed":
                        msg = await answers.get()
                closed_by_robot = msg.kind == "closed"
                reason = msg.reason or "the robot ended the video session"
        finally:
            self._viewers.pop(viewer, None)
            if not closed_by_robot:  # the page left or renegotiates: free the robot's encoder
                self.node.send_video_signal("bye", viewer)
        log.info("dashboard: video over the link ended: %s", reason)
        with contextlib.suppress(ConnectionClosed):
            await conn.send(json.dumps({"type": "video_closed", "reason": reason}))

    async def over_websocket(self, conn: ServerConnection, offer: dict[str, Any]) -> None:
        """Carry the page's WebRTC offer to the robot's video server and its answer back.

        The robot keeps the stream up for as long as this signalling
        connection lives, so it is held open until the page leaves or
        renegotiates (the task is cancelled then).
        """
        from websockets.asyncio.client import connect

        url = self.config.video_url
        try:
            async with connect(
                url, open_timeout=5, close_timeout=VIDEO_CLOSE_WAIT_S, max_size=256 * 1024
            ) as robot:
                await robot.send(json.dumps({"type": "offer", "sdp": offer.get("sdp")}))
                answer = bounded_json.loads(
                    await asyncio.wait_for(robot.recv(), VIDEO_ANSWER_TIMEOUT_S)
                )
                if not isinstance(answer, dict) or answer.get("type") != "answer":
                    raise ValueError(
                        str(answer.get("error") if isinstance(answer, dict) else answer)[:200]
                    )
                await conn.send(json.dumps({**answer, "type": "video_answer"}))
                await robot.wait_closed()
            reason = "the robot's video server closed the session"
        except asyncio.CancelledError:
            raise
        except (OSError, TimeoutError, ConnectionClosed, ValueError, InvalidStatus) as e:
            reason = f"no video from {web_token.without_token(url)}: {e}"
            log.warning("dashboard: %s", reason)
        with contextlib.suppress(ConnectionClosed):
            await conn.send(json.dumps({"type": "video_closed", "reason": reason}))
