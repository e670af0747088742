"""WebRTC signalling through the robot node's link, so video opens no port of its own.

A viewer's offer reaches the robot node as a ``VideoSignal`` on the command
path (directly, or through the router); this bridge carries it to the video
server on the robot PC (``deepxpalm video``, its WebSocket on loopback) and
hands the answer back to the node, which publishes it on its telemetry. The
media then flows peer to peer (ICE), which needs no inbound port where one
side can reach the other or a STUN/TURN server (docs/dashboard.md, Video).

The video server keeps a viewer's stream up while its signalling WebSocket
lives; here that WebSocket lives until the viewer says ``bye``, the video
server ends the session (the browser's peer connection failed), or the
viewer's key goes unheard for ``viewer_timeout_s`` (a tab that vanished
without a word). So the camera is captured and encoded only while someone
watches.

Who may watch is the video desk's call (``video_desk.py``: a controller's
key, or an observer the roster grants ``video``; offers at a bounded rate).
Here the sessions are bounded: ``max_sessions`` at once, ``per_key`` of
them one key's (a newer one closes that key's oldest), and when all are
taken a controller's offer closes an observer's session to make room. The
slot is taken on this bridge's loop with no await between the check and the
taking, so offers at once never pass the bound; the video server holds its
own bound the same way, tells the controller's offers from the others'
(``role`` in the offer), and gives back the slot of a session whose ICE has
not completed within its ``ice_timeout_s``.

Each offer opens its own connection, so a video server that died and came
back (systemd, or ``deepxpalm demo``, restarts it) needs nothing here: a
session it held ends with ``closed``. An offer while it is down waits for it
(a connection tried every ``SERVER_POLL_S``, for up to ``SERVER_WAIT_S``: its
unit's ``RestartSec`` and its start) and is carried to it the moment it
listens again, rather than at the viewer's next retry; one it does not come
back for in time is answered ``closed`` with the reason.

Nothing here blocks the frame loop: the node calls ``on_signal`` and
``take_outgoing`` (a deque each way), and the sessions run on an asyncio
loop of their own thread, started at the first offer.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import json
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from common.web import bounded_json, web_token
from common.wire.messages import VideoSignal

if TYPE_CHECKING:
    from websockets.asyncio.client import ClientConnection

log = logging.getLogger(__name__)

ANSWER_TIMEOUT_S = 10.0
#: how long an offer waits for a video server that is not listening (restarting: its unit's
#: RestartSec and its start, a few seconds) before the viewer hears that none is running;
#: well inside the dashboard's 10 s wait for the answer
SERVER_WAIT_S = 6.0
SERVER_POLL_S = 0.1  # a refused connection on loopback costs next to nothing
ABNORMAL_CLOSURE = 1006  # the video server's socket dropped without a close (it died)


@dataclass
class _Session:
    signer: bytes | None
    controller: bool = True  # a controller's session (an observer's may be closed for it)
    task: asyncio.Task[None] | None = None


class LinkSignalling:
    """Carries viewers' offers to the local video server and its answers back."""

    def __init__(
        self,
        video_url: str,
        *,
        token_file: Path | None = None,
        max_sessions: int = 4,
        per_key: int = 2,
        server_wait_s: float = SERVER_WAIT_S,
    ) -> None:
        self.video_url = video_url
        #: how long an offer waits for a video server that is not listening
        self.server_wait_s = server_wait_s
        #: the video server's token_file; None: ``video_url`` carries the token
        self.token_file = token_file
        self._shown_url = web_token.without_token(video_url)  # for logs and viewers
        self.max_sessions = max_sessions
        self.per_key = per_key
        #: signals for the node to publish, appended by the sessions' thread
        self.outgoing: collections.deque[VideoSignal] = collections.deque()
        self.counters: collections.Counter[str] = collections.Counter()
        self._sessions: dict[int, _Session] = {}  # viewer -> session (the loop's thread only)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._finishing: asyncio.Future[None] | None = None

    # ----------------------------------------------------- the node's side
    def on_signal(self, msg: VideoSignal, signer: bytes | None, controller: bool = True) -> None:
        """An offer or a bye from a viewer; never blocks.

        ``controller``: the offer is a controller's (it may close an observer's
        session when every slot is taken). Whether the key may watch at all is
        the caller's to judge (video_desk.py).
        """
        if msg.kind == "offer" and msg.sdp:
            self.counters["video_offers"] += 1
            self._call(self._open, msg.viewer, msg.sdp, signer, controller)
        elif msg.kind == "bye":
            self._call(self._end, msg.viewer, signer, None)
        else:
            self.counters["video_signals_ignored"] += 1

    def take_outgoing(self) -> list[VideoSignal]:
        out = []
        while self.outgoing:
            out.append(self.outgoing.popleft())
        return out

    def expire(
        self,
        heard_lately: Callable[[bytes | None], bool],
        may_watch: Callable[[bytes | None], bool] | None = None,
    ) -> None:
        """End the sessions of viewers whose key has gone quiet (``heard_lately`` says no),
        and of keys that may no longer watch (``may_watch`` says no: a roster reload)."""
        if self._loop is None:
            return
        self._call(self._expire, heard_lately, may_watch)

    @property
    def sessions(self) -> int:
        return len(self._sessions)

    def close(self) -> None:
        with self._lock:
            loop, thread = self._loop, self._thread
            self._loop = self._thread = None
        if loop is None or thread is None:
            return
        loop.call_soon_threadsafe(self._stop_all)
        thread.join(5)

    # ------------------------------------------------------------ internals
    def _call(self, fn: Callable[..., object], *args: object) -> None:
        with self._lock:
            if self._loop is None:
                ready = threading.Event()
                self._thread = threading.Thread(
                    target=self._run, args=(ready,), name="video-signalling", daemon=True
                )
                self._thread.start()
                ready.wait(5)
            loop = self._loop
        if loop is not None:
            loop.call_soon_threadsafe(fn, *args)

    def _run(self, ready: threading.Event) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        ready.set()
        try:
            loop.run_forever()
        finally:
            loop.close()

    def _stop_all(self) -> None:
        tasks = [s.task for s in self._sessions.values() if s.task is not None]
        for task in tasks:
            task.cancel()

        async def finish() -> None:
            await asyncio.gather(*tasks, return_exceptions=True)
            asyncio.get_running_loop().stop()

        self._finishing = asyncio.ensure_future(finish())

    def _open(self, viewer: int, sdp: str, signer: bytes | None, controller: bool) -> None:
        """The slot checked and taken in one step (no await): offers at once keep the bound."""
        old = self._sessions.get(viewer)
        if old is not None:
            if old.signer != signer:
                self.counters["video_offers_refused"] += 1
                return  # someone else's viewer number: never take over their session
            if old.task is not None:
                old.task.cancel()  # the page renegotiates
            del self._sessions[viewer]
        mine = [v for v, s in self._sessions.items() if s.signer == signer]  # oldest first
        if len(mine) >= self.per_key:
            self.counters["video_sessions_replaced"] += 1
            self._end(mine[0], signer, f"a newer video session of this key (at most "
                      f"{self.per_key} per key)")  # fmt: skip
        if len(self._sessions) >= self.max_sessions:
            others = [v for v, s in self._sessions.items() if not s.controller]
            if not controller or not others:
                self.counters["video_offers_refused"] += 1
                self.counters["video_offers_refused_full"] += 1
                whose = "" if controller else ", and a controller's come first"
                self._emit(
                    viewer,
                    "closed",
                    reason=f"all {self.max_sessions} video sessions are taken{whose}",
                )
                return
            self.counters["video_sessions_preempted"] += 1
            victim = self._sessions[others[0]]
            self._end(others[0], victim.signer, "closed to make room for a controller's video")
        session = _Session(signer, controller)
        self._sessions[viewer] = session
        session.task = asyncio.ensure_future(self._session(viewer, sdp, session))

    def _end(self, viewer: int, signer: bytes | None, reason: str | None) -> None:
        session = self._sessions.get(viewer)
        if session is None or session.signer != signer:
            return
        del self._sessions[viewer]
        if session.task is not None:
            session.task.cancel()
        if reason is not None:
            self._emit(viewer, "closed", reason=reason)

    def _expire(
        self,
        heard_lately: Callable[[bytes | None], bool],
        may_watch: Callable[[bytes | None], bool] | None,
    ) -> None:
        for viewer, session in list(self._sessions.items()):
            if not heard_lately(session.signer):
                self.counters["video_sessions_expired"] += 1
                self._end(viewer, session.signer, "the viewer went quiet")
            elif may_watch is not None and not may_watch(session.signer):
                self.counters["video_sessions_revoked"] += 1
                self._end(viewer, session.signer, "this key may no longer watch (the roster)")

    def _emit(self, viewer: int, kind: str, **fields: object) -> None:
        self.outgoing.append(VideoSignal(seq=0, t_send_ns=0, kind=kind, viewer=viewer, **fields))

    def url(self) -> str:
        """The video server's URL with its token, read each time (a restart may renew it)."""
        if self.token_file is None:
            return self.video_url
        return web_token.with_token(
            self.video_url, web_token.token_file(self.token_file, "link.video_token_file")
        )

    async def _connect(self, viewer: int) -> ClientConnection:
        """The video server's signalling socket, waiting up to ``server_wait_s`` for a server
        that is not listening (restarting); ``ConnectionRefusedError`` after that."""
        from websockets.asyncio.client import connect

        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.server_wait_s
        waiting = False
        while True:
            try:
                return await connect(self.url(), open_timeout=5, max_size=256 * 1024)
            except ConnectionRefusedError:
                left = deadline - loop.time()
                if left <= 0:
                    raise
                if not waiting:
                    waiting = True
                    self.counters["video_offers_waited"] += 1
                    log.info(
                        "video: viewer %016x waits for the video server at %s (restarting?)",
                        viewer,
                        self._shown_url,
                    )
                await asyncio.sleep(min(SERVER_POLL_S, left))

    async def _session(self, viewer: int, sdp: str, session: _Session) -> None:
        from websockets.exceptions import ConnectionClosed, InvalidStatus

        reason = "the video server ended the session"
        try:
            async with await self._connect(viewer) as ws:
                role = "controller" if session.controller else "observer"
                await ws.send(json.dumps({"type": "offer", "sdp": sdp, "role": role}))
                answer = bounded_json.loads(await asyncio.wait_for(ws.recv(), ANSWER_TIMEOUT_S))
                if not isinstance(answer, dict) or answer.get("type") != "answer":
                    error = answer.get("error") if isinstance(answer, dict) else answer
                    raise ValueError(f"it refused the offer: {str(error)[:120]}")
                self._emit(
                    viewer,
                    "answer",
                    sdp=str(answer["sdp"]),
                    source=str(answer.get("source", ""))[:64] or None,
                    width=int(answer["width"]),
                    height=int(answer["height"]),
                    fps=float(answer["fps"]),
                )
                self.counters["video_answers"] += 1
                log.info("video: viewer %016x connected through the link", viewer)
                await ws.wait_closed()
                if ws.close_reason:
                    reason = f"the video server ended the session: {ws.close_reason}"
                elif ws.close_code == ABNORMAL_CLOSURE:
                    reason = "the video server stopped (its connection dropped)"
        except asyncio.CancelledError:
            log.info("video: viewer %016x left", viewer)
            raise
        except ConnectionClosed as e:
            reason = f"the video server refused: {e.rcvd.reason if e.rcvd else e}"
        except InvalidStatus as e:
            reason = (
                f"the video server at {self._shown_url} refused the signalling "
                f"(HTTP {e.response.status_code}): link.video_token_file must name its token_file"
            )
            log.warning("video: %s", reason)
        except ConnectionRefusedError:
            reason = (
                f"no video server is running at {self._shown_url} (waited "
                f"{self.server_wait_s:g} s for it to restart)"
            )
            log.warning("video: %s", reason)
        except (OSError, TimeoutError, ValueError, KeyError, TypeError) as e:
            reason = f"no video server at {self._shown_url}: {e}"
            log.warning("video: %s", reason)
        if self._sessions.get(viewer) is session:
            del self._sessions[viewer]
        with contextlib.suppress(Exception):
            self._emit(viewer, "closed", reason=reason[:200])
