"""What the dashboard's pages are shown: the node sampled, and its state pushed.

A sampler on the web server's loop takes ``node.snapshot()`` at up to
``max_rate_hz`` for the link history and, at most ``push_rate_hz`` times a
second and only while a page is connected, pushes a JSON state to every page
when something drawn changed (the stimulus, the pattern, the servo goals, the
link state), plus a refresh four times a second for the ages and counters,
and a full state with the last minute's link history once a second.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from typing import Any

from operator_side.dashboard.config import DashboardConfig
from operator_side.dashboard.view import CONTENT_KEYS, LinkHistory, snapshot_view
from operator_side.dashboard.web import WebServer

log = logging.getLogger(__name__)

REFRESH_S = 0.25  # ages and counters move even when the stimulus does not
FULL_STATE_S = 1.0  # a page that missed a push (it lagged) is whole again within this


class StatePush:
    """The node's snapshots, their link history, and the state pushed to every page."""

    def __init__(self, node: Any, config: DashboardConfig, server: WebServer) -> None:
        self.node = node
        self.config = config
        self.server = server
        self.history = LinkHistory()
        self.samples = 0
        self.pushes = 0
        self._seq = 0
        self._last_content: tuple | None = None
        self._last_frame: Any = None
        self._last_push = 0.0
        self._last_full = 0.0
        self._history_changed = False  # a second closed since the last push
        #: the newest view pushed (or sent to a page as it connected)
        self.latest: dict[str, Any] | None = None
        self._next_push = 0.0  # the next push slot (monotonic s)
        #: a sample this close before its slot takes it: the sampler's own jitter never
        #: turns every second slot into every third sample
        push_hz = min(config.push_rate_hz, config.max_rate_hz)
        self._push_period = 1.0 / push_hz - 0.5 / config.max_rate_hz

    def first_state(self) -> str:
        """The state a page gets as it connects: the node as it is now (with no page
        connected no view was kept up to date), with the link history."""
        self.latest = snapshot_view(self.node.snapshot())
        first = {"type": "state", "seq": self._seq, **self.latest}
        first["history"] = self.history.view()
        return json.dumps(first, separators=(",", ":"))

    async def sample_loop(self) -> None:
        period = 1.0 / self.config.max_rate_hz
        deadline = time.monotonic()
        while True:
            try:
                self.sample(time.monotonic())
            except Exception:  # a bad snapshot must not end the dashboard
                log.exception("dashboard: sampling the node failed")
                await asyncio.sleep(1.0)
            deadline += period
            delay = deadline - time.monotonic()
            if delay < 0:  # fell behind: skip the missed slots rather than burst
                deadline = time.monotonic()
                delay = 0
            await asyncio.sleep(delay)

    def sample(self, now: float) -> None:
        snap = self.node.snapshot()
        self.samples += 1
        self._history_changed |= self.history.add(now, snap)
        if now < self._next_push or not self.server.connections:
            return  # not a push slot, or nobody to draw it: the history alone
        self._next_push = now + self._push_period
        view = snapshot_view(snap)
        content = tuple(json.dumps(view[k]) for k in CONTENT_KEYS)
        frame_changed = view["frame"] != self._last_frame
        self.latest = view
        full = self._history_changed or now - self._last_full >= FULL_STATE_S
        due = (
            content != self._last_content
            or frame_changed
            or full
            or now - self._last_push >= REFRESH_S
        )
        if not due:
            return
        self._history_changed = False
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
