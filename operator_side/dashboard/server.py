"""The live dashboard: the operator node's state on a web page, gripper buttons back.

The dashboard is the page's web server and its parts: what the pages are
shown (``push``: the node sampled, its state pushed while a page is
connected), what a page may send (``page_commands``) and a page's video
(``video_relay``). The node knows nothing of the dashboard: it only needs
``snapshot()`` and ``send_command()``, so a test or a replay can feed the
page with any object that has them.
"""

from __future__ import annotations

import asyncio
import json
import logging
from typing import Protocol

from websockets.asyncio.server import ServerConnection
from websockets.exceptions import ConnectionClosed

from common.errors import ConfigError
from common.web import bounded_json, web_token
from operator_side.dashboard.config import TOKEN_ENV, VIDEO_OVER_LINK, DashboardConfig
from operator_side.dashboard.page_auth import PageAuth
from operator_side.dashboard.page_commands import Page, PageCommands
from operator_side.dashboard.push import StatePush
from operator_side.dashboard.snapshot import Snapshot
from operator_side.dashboard.video_relay import VIDEO_CLOSE_WAIT_S, VideoRelay, is_video_offer
from operator_side.dashboard.view import hello_view
from operator_side.dashboard.web import WebServer, package_files
from operator_side.palm.renderer import RendererConfig

log = logging.getLogger(__name__)

STATIC_FILES = ("index.html", "app.js", "jog.js", "video.js", "patterns.js", "style.css")


class DashboardSource(Protocol):
    """What the dashboard needs from a node (``OperatorNode`` has it)."""

    def snapshot(self) -> Snapshot: ...

    def send_command(
        self,
        action: str,
        grip_level: int | None = None,
        velocity: tuple[float, ...] | None = None,
        age_ms: float = 0.0,
    ) -> None: ...


class Dashboard:
    """Serves the page and keeps it current; ``start()`` / ``stop()`` from any thread."""

    def __init__(
        self,
        node: DashboardSource,
        config: DashboardConfig | None = None,
        *,
        renderer: RendererConfig | None = None,
        stale_after_ms: float | None = None,
    ) -> None:
        self.node = node
        if hasattr(node, "frames_consumed"):  # the page's heatmap: the node subscribes frames
            node.frames_consumed = True
        self.config = config or DashboardConfig()
        node_config = getattr(node, "config", None)
        self.renderer = renderer or getattr(node_config, "renderer", None) or RendererConfig()
        if stale_after_ms is None:
            link = getattr(node_config, "link", None)
            stale_after_ms = getattr(link, "stale_after_ms", 150.0)
        hello = hello_view(self.renderer, stale_after_ms, self.config.max_rate_hz, self.config.jog)
        hello["video"] = bool(self.config.video_url)
        hello["ice_servers"] = self.config.ice.as_dicts() if self.config.video_url else []
        hello["ice_transport_policy"] = self.config.ice.transport_policy
        hello["video_stale_ms"] = self.config.video_stale_ms
        self.hello = json.dumps(hello, separators=(",", ":"))
        if self.config.video_url == VIDEO_OVER_LINK and not hasattr(node, "send_video_signal"):
            raise ConfigError("dashboard video_url = 'link' needs an operator node's link")
        self.server = WebServer(
            self.config.host,
            self.config.port,
            package_files("operator_side.dashboard", STATIC_FILES),
            self._client,
            name="dashboard",
            background=[lambda: self.push.sample_loop()],
            auth=PageAuth(
                web_token.configured_token(self.config.token, TOKEN_ENV, "dashboard.token"),
                self.config.allowed_hosts,
                name="dashboard",
            ),
        )
        #: what the pages are shown, what they may send, and their video
        self.push = StatePush(node, self.config, self.server)
        self.commands = PageCommands(node, self.config, lambda: self.push.latest)
        self.video = VideoRelay(node, self.config, self.server)
        if self.config.video_url == VIDEO_OVER_LINK:
            node.video_signal_handler = self.video.on_video_signal

    @property
    def url(self) -> str:
        """The page's address with its token: what the operator opens."""
        return self.server.url

    @property
    def ws_url(self) -> str:
        return self.server.ws_url

    def start(self) -> None:
        self.server.start()

    def stop(self) -> None:
        self.server.stop()

    def __enter__(self) -> Dashboard:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ------------------------------------------------------------- clients
    async def _client(self, conn: ServerConnection) -> None:
        peer = conn.remote_address
        log.info("dashboard: page connected from %s", peer)
        await conn.send(self.hello)
        await conn.send(self.push.first_state())
        page = Page()
        watchdog = asyncio.create_task(self.commands.jog_watchdog(page))
        try:
            async for raw in conn:
                if self.config.video_url and is_video_offer(raw):
                    if page.video is not None:
                        page.video.cancel()  # the page renegotiates: drop the old session
                    offer = bounded_json.loads(raw)
                    page.video = asyncio.create_task(self.video.relay(conn, offer))
                    continue
                reply = self.commands.on_message(raw, page)
                if reply is not None:
                    await conn.send(json.dumps(reply, separators=(",", ":")))
        except ConnectionClosed:
            pass
        finally:
            watchdog.cancel()
            if page.jogging:  # a closed or crashed tab must not leave the arm moving
                self.commands.end_jog(page, "page disconnected while jogging")
            if page.video is not None:
                # cancelled and then waited for (briefly): its close handshake with the video
                # server finishes here, not never (a loop that ends leaves the socket open)
                page.video.cancel()
                await asyncio.wait({page.video}, timeout=VIDEO_CLOSE_WAIT_S)
            log.info("dashboard: page from %s disconnected", peer)
