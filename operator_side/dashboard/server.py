"""The live dashboard: the operator node's state on a web page, gripper buttons back.

A sampler on the web server's loop takes ``node.snapshot()`` at up to
``max_rate_hz`` and pushes a JSON state to every page only when something
drawn changed (the stimulus, the pattern, the servo goals, the link state),
plus a refresh four times a second for the ages and counters, and a full
state with the last minute's link history once a second. The node knows
nothing of the dashboard: it only needs ``snapshot()`` and ``send_command()``,
so a test or a replay can feed the page with any object that has them.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from typing import Any, Protocol

from websockets.asyncio.server import ServerConnection
from websockets.exceptions import ConnectionClosed

from operator_side.dashboard.config import DashboardConfig
from operator_side.dashboard.view import CONTENT_KEYS, LinkHistory, hello_view, snapshot_view
from operator_side.dashboard.web import WebServer, package_files
from operator_side.node import Snapshot
from operator_side.renderer import RendererConfig

log = logging.getLogger(__name__)

STATIC_FILES = ("index.html", "app.js", "patterns.js", "style.css")
REFRESH_S = 0.25  # ages and counters move even when the stimulus does not
FULL_STATE_S = 1.0  # a page that missed a push (it lagged) is whole again within this
GRIP_LEVELS = range(1, 32)
COMMANDS_PER_S = 10  # a stuck key or a buggy page cannot flood the robot's command link


class DashboardSource(Protocol):
    """What the dashboard needs from a node (``OperatorNode`` has it)."""

    def snapshot(self) -> Snapshot: ...

    def send_command(
        self,
        action: str,
        grip_level: int | None = None,
        velocity: tuple[float, ...] | None = None,
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
        self.config = config or DashboardConfig()
        node_config = getattr(node, "config", None)
        self.renderer = renderer or getattr(node_config, "renderer", None) or RendererConfig()
        if stale_after_ms is None:
            link = getattr(node_config, "link", None)
            stale_after_ms = getattr(link, "stale_after_ms", 150.0)
        self.hello = json.dumps(
            hello_view(self.renderer, stale_after_ms, self.config.max_rate_hz),
            separators=(",", ":"),
        )
        self.history = LinkHistory()
        self.server = WebServer(
            self.config.host,
            self.config.port,
            package_files("operator_side.dashboard", STATIC_FILES),
            self._client,
            name="dashboard",
            background=[self._sample_loop],
        )
        self.samples = 0
        self.pushes = 0
        self._seq = 0
        self._last_content: tuple | None = None
        self._last_frame: Any = None
        self._last_push = 0.0
        self._last_full = 0.0
        self._latest: dict[str, Any] | None = None

    @property
    def url(self) -> str:
        return self.server.url

    def start(self) -> None:
        self.server.start()

    def stop(self) -> None:
        self.server.stop()

    def __enter__(self) -> Dashboard:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ------------------------------------------------------------ sampling
    async def _sample_loop(self) -> None:
        period = 1.0 / self.config.max_rate_hz
        deadline = time.monotonic()
        while True:
            try:
                self._sample(time.monotonic())
            except Exception:  # a bad snapshot must not end the dashboard
                log.exception("dashboard: sampling the node failed")
                await asyncio.sleep(1.0)
            deadline += period
            delay = deadline - time.monotonic()
            if delay < 0:  # fell behind: skip the missed slots rather than burst
                deadline = time.monotonic()
                delay = 0
            await asyncio.sleep(delay)

    def _sample(self, now: float) -> None:
        snap = self.node.snapshot()
        self.samples += 1
        history_changed = self.history.add(now, snap)
        view = snapshot_view(snap)
        content = tuple(json.dumps(view[k]) for k in CONTENT_KEYS)
        frame_changed = view["frame"] != self._last_frame
        full = history_changed or now - self._last_full >= FULL_STATE_S
        due = (
            content != self._last_content
            or frame_changed
            or full
            or now - self._last_push >= REFRESH_S
        )
        self._latest = view
        if not due:
            return
        self._seq += 1
        msg = {"type": "state", "seq": self._seq, **view}
        if full:
            msg["history"] = self.history.view()
            self._last_full = now
        elif not frame_changed:
            del msg["frame"]  # the bulk of a message; unchanged, the page keeps its copy
        self._last_content, self._last_frame, self._last_push = content, view["frame"], now
        text = json.dumps(msg, separators=(",", ":"))
        for conn in list(self.server.connections):
            if self.server.send(conn, text):
                self.pushes += 1

    # ------------------------------------------------------------- clients
    async def _client(self, conn: ServerConnection) -> None:
        peer = conn.remote_address
        log.info("dashboard: page connected from %s", peer)
        await conn.send(self.hello)
        if self._latest is not None:
            first = {"type": "state", "seq": self._seq, **self._latest}
            first["history"] = self.history.view()
            await conn.send(json.dumps(first, separators=(",", ":")))
        sent_at: list[float] = []
        try:
            async for raw in conn:
                reply = self._on_message(raw, sent_at)
                await conn.send(json.dumps(reply, separators=(",", ":")))
        except ConnectionClosed:
            pass
        finally:
            log.info("dashboard: page from %s disconnected", peer)

    def _on_message(self, raw: str | bytes, sent_at: list[float]) -> dict[str, Any]:
        try:
            msg = json.loads(raw)
        except (ValueError, UnicodeDecodeError):
            return {"type": "ack", "ok": False, "error": "not JSON"}
        if not isinstance(msg, dict) or msg.get("type") != "command":
            return {"type": "ack", "ok": False, "error": "expected a command"}
        action = msg.get("action")
        now = time.monotonic()
        sent_at[:] = [t for t in sent_at if now - t < 1.0]
        if len(sent_at) >= COMMANDS_PER_S:
            return {"type": "ack", "ok": False, "action": action, "error": "too many commands"}
        if action == "gripper_open":
            self.node.send_command("gripper_open")
            level = None
        elif action == "gripper_close":
            level = msg.get("grip_level", 16)
            if isinstance(level, bool) or not isinstance(level, int) or level not in GRIP_LEVELS:
                return {
                    "type": "ack",
                    "ok": False,
                    "action": action,
                    "error": "grip_level must be an integer 1..31",
                }
            self.node.send_command("gripper_close", grip_level=level)
        else:
            return {"type": "ack", "ok": False, "action": action, "error": "unknown action"}
        sent_at.append(now)
        log.info("dashboard: %s%s", action, "" if level is None else f" (grip level {level})")
        return {"type": "ack", "ok": True, "action": action, "grip_level": level}
