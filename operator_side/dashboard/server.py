"""The live dashboard: the operator node's state on a web page, gripper buttons back.

A sampler on the web server's loop takes ``node.snapshot()`` at up to
``max_rate_hz`` for the link history and, at most ``push_rate_hz`` times a
second and only while a page is connected, pushes a JSON state to every page
when something drawn changed (the stimulus, the pattern, the servo goals, the
link state), plus a refresh four times a second for the ages and counters,
and a full state with the last minute's link history once a second. The node knows
nothing of the dashboard: it only needs ``snapshot()`` and ``send_command()``,
so a test or a replay can feed the page with any object that has them.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import secrets
import time
from dataclasses import dataclass, field
from typing import Any, Protocol

from websockets.asyncio.server import ServerConnection
from websockets.exceptions import ConnectionClosed, InvalidStatus

from common import bounded_json, web_token
from common.errors import ConfigError
from common.messages import MAX_SDP_CHARS, VideoSignal
from common.tactile import GRIP_LEVELS
from operator_side.dashboard.config import TOKEN_ENV, VIDEO_OVER_LINK, DashboardConfig
from operator_side.dashboard.page_auth import PageAuth
from operator_side.dashboard.view import CONTENT_KEYS, LinkHistory, hello_view, snapshot_view
from operator_side.dashboard.web import WebServer, package_files
from operator_side.node import Snapshot
from operator_side.palm.renderer import RendererConfig

log = logging.getLogger(__name__)

STATIC_FILES = ("index.html", "app.js", "jog.js", "video.js", "patterns.js", "style.css")
VIDEO_ANSWER_TIMEOUT_S = 10.0
#: how long a page's video session may take to close its socket to the video server
VIDEO_CLOSE_WAIT_S = 1.0
REFRESH_S = 0.25  # ages and counters move even when the stimulus does not
FULL_STATE_S = 1.0  # a page that missed a push (it lagged) is whole again within this
COMMANDS_PER_S = 10  # a stuck key or a buggy page cannot flood the robot's command link
JOG_WATCHDOG_PERIODS = 6  # a jogging page silent this many send periods (200 ms) is stopped
#: how fast a page's clock may drift from the server's before its fresh jogs look late
#: (1000 ppm; real clocks drift under 100)
PAGE_CLOCK_DRIFT = 1e-3


class PageClock:
    """How much later than usual a page's messages reach the server, in ms.

    The page stamps its arm messages with its own monotonic clock. Its offset
    from ours is unknown (the page may run on another machine), so the fastest
    arrival seen stands for "no delay": a message that took longer sat in a
    queue (this process starved, the page's socket backed up). The floor may
    rise by ``PAGE_CLOCK_DRIFT`` per second, so two clocks that drift apart
    never make fresh messages look late.
    """

    def __init__(self) -> None:
        self._floor_ms: float | None = None  # the smallest (arrival - stamp) seen
        self._floor_at_ms = 0.0

    def delay_ms(self, t_page_ms: Any, now_ms: float) -> float | None:
        """This message's delay beyond the fastest seen; None when the stamp is not a time."""
        if isinstance(t_page_ms, bool) or not isinstance(t_page_ms, (int, float)):
            return None
        try:
            stamp = float(t_page_ms)  # a 400-digit integer does not fit: not a time either
        except OverflowError:
            return None
        if not math.isfinite(stamp):
            return None
        sample = now_ms - stamp
        if self._floor_ms is None:
            self._floor_ms = sample
        else:
            allowed = self._floor_ms + PAGE_CLOCK_DRIFT * (now_ms - self._floor_at_ms)
            self._floor_ms = min(allowed, sample)
        self._floor_at_ms = now_ms
        return sample - self._floor_ms


@dataclass
class _Page:
    """One connected page: its gripper command budget and whether it is jogging the arm."""

    sent_at: list[float] = field(default_factory=list)
    jog_at: list[float] = field(default_factory=list)
    jogging: bool = False
    last_jog: float = 0.0
    video: asyncio.Task | None = None  # the relayed signalling session to the robot
    clock: PageClock = field(default_factory=PageClock)


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
        self.history = LinkHistory()
        #: video sessions over the link awaiting the robot's word, by viewer number
        self._viewers: dict[int, asyncio.Queue[VideoSignal]] = {}
        if self.config.video_url == VIDEO_OVER_LINK:
            if not hasattr(node, "send_video_signal"):
                raise ConfigError("dashboard video_url = 'link' needs an operator node's link")
            node.video_signal_handler = self._on_video_signal
        self.server = WebServer(
            self.config.host,
            self.config.port,
            package_files("operator_side.dashboard", STATIC_FILES),
            self._client,
            name="dashboard",
            background=[self._sample_loop],
            auth=PageAuth(
                web_token.configured_token(self.config.token, TOKEN_ENV, "dashboard.token"),
                self.config.allowed_hosts,
                name="dashboard",
            ),
        )
        self.samples = 0
        self.pushes = 0
        self._seq = 0
        self._last_content: tuple | None = None
        self._last_frame: Any = None
        self._last_push = 0.0
        self._last_full = 0.0
        self._history_changed = False  # a second closed since the last push
        #: the newest view pushed (or sent to a page as it connected)
        self._latest: dict[str, Any] | None = None
        self._next_push = 0.0  # the next push slot (monotonic s)
        #: a sample this close before its slot takes it: the sampler's own jitter never
        #: turns every second slot into every third sample
        push_hz = min(self.config.push_rate_hz, self.config.max_rate_hz)
        self._push_period = 1.0 / push_hz - 0.5 / self.config.max_rate_hz
        jog = self.config.jog
        self._jog_watchdog_s = max(JOG_WATCHDOG_PERIODS / jog.send_rate_hz, 0.1)
        self._jogs_per_s = 2 * jog.send_rate_hz  # twice the page's rate: slack for bursts
        self.jogs_forwarded = 0
        self.assists_forwarded = 0  # arm_assist enables sent for a page holding the assist
        self.jog_ends = 0
        self.arm_stops = 0
        self.episode_marks = 0  # marks the node recorded (operator/episode_mark)

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
        self._history_changed |= self.history.add(now, snap)
        if now < self._next_push or not self.server.connections:
            return  # not a push slot, or nobody to draw it: the history alone
        self._next_push = now + self._push_period
        view = snapshot_view(snap)
        content = tuple(json.dumps(view[k]) for k in CONTENT_KEYS)
        frame_changed = view["frame"] != self._last_frame
        self._latest = view
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
    async def _client(self, conn: ServerConnection) -> None:
        peer = conn.remote_address
        log.info("dashboard: page connected from %s", peer)
        await conn.send(self.hello)
        # the node as it is now: with no page connected, no view was kept up to date
        self._latest = snapshot_view(self.node.snapshot())
        first = {"type": "state", "seq": self._seq, **self._latest}
        first["history"] = self.history.view()
        await conn.send(json.dumps(first, separators=(",", ":")))
        page = _Page()
        watchdog = asyncio.create_task(self._jog_watchdog(page))
        try:
            async for raw in conn:
                if self.config.video_url and _is_video_offer(raw):
                    if page.video is not None:
                        page.video.cancel()  # the page renegotiates: drop the old session
                    offer = bounded_json.loads(raw)
                    page.video = asyncio.create_task(self._relay_video(conn, offer))
                    continue
                reply = self._on_message(raw, page)
                if reply is not None:
                    await conn.send(json.dumps(reply, separators=(",", ":")))
        except ConnectionClosed:
            pass
        finally:
            watchdog.cancel()
            if page.jogging:  # a closed or crashed tab must not leave the arm moving
                self._end_jog(page, "page disconnected while jogging")
            if page.video is not None:
                # cancelled and then waited for (briefly): its close handshake with the video
                # server finishes here, not never (a loop that ends leaves the socket open)
                page.video.cancel()
                await asyncio.wait({page.video}, timeout=VIDEO_CLOSE_WAIT_S)
            log.info("dashboard: page from %s disconnected", peer)

    def _on_video_signal(self, msg: VideoSignal) -> None:
        """On the node's thread: a robot's answer (or close) to the session awaiting it."""
        waiting = self._viewers.get(msg.viewer)
        if waiting is not None:
            self.server.call(waiting.put_nowait, msg)

    async def _relay_video(self, conn: ServerConnection, offer: dict[str, Any]) -> None:
        if self.config.video_url == VIDEO_OVER_LINK:
            await self._video_over_link(conn, offer)
        else:
            await self._video_over_websocket(conn, offer)

    async def _video_over_link(self, conn: ServerConnection, offer: dict[str, Any]) -> None:
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

    async def _video_over_websocket(self, conn: ServerConnection, offer: dict[str, Any]) -> None:
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

    async def _jog_watchdog(self, page: _Page) -> None:
        """Stop the arm when a jogging page goes quiet (a hung tab keeps its socket open)."""
        period = self._jog_watchdog_s / 4
        while True:
            await asyncio.sleep(period)
            if page.jogging and time.monotonic() - page.last_jog > self._jog_watchdog_s:
                self._end_jog(page, "page stopped sending jogs")

    def _end_jog(self, page: _Page, why: str) -> None:
        """The page's jog is over: the arm stops, and nothing is latched."""
        page.jogging = False
        self.node.send_command("arm_jog_end")
        self.jog_ends += 1
        log.info("dashboard: arm_jog_end (%s)", why)

    def _stop_arm(self, page: _Page) -> None:
        """STOP pressed on the page: latched on the robot, whoever else is jogging."""
        page.jogging = False
        self.node.send_command("arm_stop")
        self.arm_stops += 1
        log.warning("dashboard: STOP (arm_stop) from a page: latched on the robot until a resume")

    def _resume_refusal(self) -> str | None:
        """Why the robot would refuse our ``arm_resume``, as far as its newest heartbeat tells."""
        control = (self._latest or {}).get("control")
        if control is None or control["ours"]:  # unsigned: the one operator holds the arm
            return None
        if control["holder"] is None:
            return "only the lease holder may resume the arm, and nobody holds it: ask for control"
        return f"only the lease holder may resume the arm: {control['holder']}… holds it, not you"

    def _on_message(self, raw: str | bytes, page: _Page) -> dict[str, Any] | None:
        """The reply to one page message; None for a jog that went through (30 a second)."""
        try:
            msg = bounded_json.loads(raw)  # any depth: an error reply, the socket stays open
        except bounded_json.TooDeep as e:
            return {"type": "ack", "ok": False, "error": f"not JSON we take: {e}"}
        except ValueError:  # UnicodeDecodeError included
            return {"type": "ack", "ok": False, "error": "not JSON"}
        if not isinstance(msg, dict) or msg.get("type") != "command":
            return {"type": "ack", "ok": False, "error": "expected a command"}
        action = msg.get("action")
        if not isinstance(action, str):
            return {"type": "ack", "ok": False, "error": "action must be a string"}
        now = time.monotonic()
        # every arm message keeps the page's clock current; a stop with a bad stamp still stops
        delay_ms = (
            page.clock.delay_ms(msg.get("t_page_ms"), now * 1000.0)
            if action in ARM_ACTIONS
            else None
        )
        if action in ("arm_jog", "arm_assist") and delay_ms is None:
            return {
                "type": "ack",
                "ok": False,
                "action": action,
                "error": "an arm jog or assist must carry t_page_ms, a finite number (the "
                "page's performance.now())",
            }
        if action == "arm_stop":  # never rate-limited: stopping must always get through
            self._stop_arm(page)
            return {"type": "ack", "ok": True, "action": action}
        if action == "arm_jog_end":  # nor is the end of a jog
            self._end_jog(page, "released on the page")
            return {"type": "ack", "ok": True, "action": action}
        if action == "arm_jog":
            return self._on_jog(msg, page, now, delay_ms)
        if action == "arm_assist":
            return self._on_assist(page, now, delay_ms)
        if action == "episode_mark":
            return self._on_episode_mark(msg, page, now)
        sent_at = page.sent_at
        sent_at[:] = [t for t in sent_at if now - t < 1.0]
        if len(sent_at) >= COMMANDS_PER_S:
            return {"type": "ack", "ok": False, "action": action, "error": "too many commands"}
        if action == "arm_resume":
            refusal = self._resume_refusal()
            if refusal is not None:  # the robot would refuse it: say why instead of sending it
                return {"type": "ack", "ok": False, "action": action, "error": refusal}
            self.node.send_command("arm_resume")
            level = None
        elif action == "gripper_open":
            self.node.send_command("gripper_open")
            level = None
        elif action in ("lease_request", "lease_grant", "lease_release"):
            # the robot decides (robot_side/node/commands/lease.py): a grant goes to whoever asked
            self.node.send_command(action)
            level = None
        elif action == "gripper_close":
            level = msg.get("grip_level", 16)
            if isinstance(level, bool) or not isinstance(level, int) or level not in GRIP_LEVELS:
                return {
                    "type": "ack",
                    "ok": False,
                    "action": action,
                    "error": f"grip_level must be an integer 1..{GRIP_LEVELS[-1]}",
                }
            self.node.send_command("gripper_close", grip_level=level)
        else:
            return {"type": "ack", "ok": False, "action": action, "error": "unknown action"}
        sent_at.append(now)
        log.info("dashboard: %s%s", action, "" if level is None else f" (grip level {level})")
        return {"type": "ack", "ok": True, "action": action, "grip_level": level}

    def _on_episode_mark(self, msg: dict[str, Any], page: _Page, now: float) -> dict[str, Any]:
        """The operator's mark on the episode in progress, recorded by the node (not sent).

        It shares the page's command budget, so a stuck key cannot flood the
        recording; refused with a reason when the node does not record.
        """
        from common.episode_marks import check_mark

        kind, task = msg.get("kind"), msg.get("task")
        if task == "":
            task = None  # an empty task field on the page: the export's default task
        reply: dict[str, Any] = {"type": "ack", "ok": False, "action": "episode_mark", "kind": kind}
        problem = check_mark(kind, task)
        if problem is not None:
            return {**reply, "error": problem}
        page.sent_at[:] = [t for t in page.sent_at if now - t < 1.0]
        if len(page.sent_at) >= COMMANDS_PER_S:
            return {**reply, "error": "too many commands"}
        page.sent_at.append(now)
        mark = getattr(self.node, "mark_episode", None)
        if mark is None or not mark(kind, task):
            return {
                **reply,
                "error": "not recording, so the mark would be lost: start the operator node "
                "with --record (deepxpalm demo --record DIR) to mark episodes",
            }
        self.episode_marks += 1
        log.info("dashboard: episode marked %s%s", kind, "" if task is None else f" ({task!r})")
        return {**reply, "ok": True, "task": task}

    def _on_assist(self, page: _Page, now: float, age_ms: float) -> dict[str, Any] | None:
        """The assist held on the page: an enable, rate-limited and watched as a jog is.

        Let go, the page sends ``arm_jog_end`` (which ends the assist on the
        robot); a page that goes quiet is ended by the jog watchdog.
        """
        page.jog_at[:] = [t for t in page.jog_at if now - t < 1.0]
        if len(page.jog_at) >= self._jogs_per_s:
            return {"type": "ack", "ok": False, "action": "arm_assist", "error": "too many jogs"}
        page.jog_at.append(now)
        self.node.send_command("arm_assist", age_ms=age_ms)
        page.jogging, page.last_jog = True, now
        self.assists_forwarded += 1
        return None

    def _on_jog(
        self, msg: dict[str, Any], page: _Page, now: float, age_ms: float
    ) -> dict[str, Any] | None:
        velocity = msg.get("velocity")
        if (
            not isinstance(velocity, list)
            or len(velocity) != 6
            or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                for v in velocity
            )
        ):
            return {
                "type": "ack",
                "ok": False,
                "action": "arm_jog",
                "error": "velocity must be 6 finite numbers (m/s, rad/s)",
            }
        page.jog_at[:] = [t for t in page.jog_at if now - t < 1.0]
        if len(page.jog_at) >= self._jogs_per_s:
            return {"type": "ack", "ok": False, "action": "arm_jog", "error": "too many jogs"}
        page.jog_at.append(now)
        twist = cap_twist(
            velocity, self.config.jog.max_linear_speed_m_s, self.config.jog.max_angular_speed_rad_s
        )
        if not any(twist):
            if page.jogging:
                self._end_jog(page, "zero jog")
            return None
        self.node.send_command("arm_jog", velocity=twist, age_ms=age_ms)
        page.jogging, page.last_jog = True, now
        self.jogs_forwarded += 1
        return None


ARM_ACTIONS = ("arm_jog", "arm_assist", "arm_jog_end", "arm_stop")


def _is_video_offer(raw: str | bytes) -> bool:
    try:
        msg = bounded_json.loads(raw)
    except ValueError:  # too deep, not UTF-8 or not JSON: _on_message says which
        return False
    return isinstance(msg, dict) and msg.get("type") == "video_offer"


def cap_twist(velocity: list[float], max_linear: float, max_angular: float) -> tuple[float, ...]:
    """Scale the linear and angular parts (direction kept) to the operator's caps."""
    out = [float(v) for v in velocity]
    for part, cap in ((slice(0, 3), max_linear), (slice(3, 6), max_angular)):
        norm = math.sqrt(sum(v * v for v in out[part]))
        if norm > cap:
            out[part] = [v * cap / norm for v in out[part]]
    return tuple(out)
