"""What a dashboard page may send: gripper and lease commands, jogs, the assist, STOP, marks.

Each page has a command budget (``COMMANDS_PER_S``; a stuck key or a buggy
page cannot flood the robot's command link), its own jog rate and a jog
watchdog: a jogging page that goes quiet (a hung tab keeps its socket open)
stops the arm. A STOP and the end of a jog are never rate-limited. Arm
messages carry the page's clock, so a jog that sat in a queue reaches the
robot with its age (``PageClock``).
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from common.tactile.contract import GRIP_LEVELS
from common.web import bounded_json
from operator_side.dashboard.config import DashboardConfig

log = logging.getLogger(__name__)

COMMANDS_PER_S = 10  # a stuck key or a buggy page cannot flood the robot's command link
JOG_WATCHDOG_PERIODS = 6  # a jogging page silent this many send periods (200 ms) is stopped
#: how fast a page's clock may drift from the server's before its fresh jogs look late
#: (1000 ppm; real clocks drift under 100)
PAGE_CLOCK_DRIFT = 1e-3
ARM_ACTIONS = ("arm_jog", "arm_assist", "arm_jog_end", "arm_stop")


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
class Page:
    """One connected page: its gripper command budget and whether it is jogging the arm."""

    sent_at: list[float] = field(default_factory=list)
    jog_at: list[float] = field(default_factory=list)
    jogging: bool = False
    last_jog: float = 0.0
    video: asyncio.Task | None = None  # the relayed signalling session to the robot
    clock: PageClock = field(default_factory=PageClock)


class PageCommands:
    """Every page's commands to the node: checked, rate-limited, counted, then sent.

    ``latest()`` is the newest view pushed to the pages (the robot's lease as
    its heartbeat tells it), so a resume the robot would refuse is refused
    here with the reason.
    """

    def __init__(
        self, node: Any, config: DashboardConfig, latest: Callable[[], dict[str, Any] | None]
    ) -> None:
        self.node = node
        self.config = config
        self._latest = latest
        jog = config.jog
        self._jog_watchdog_s = max(JOG_WATCHDOG_PERIODS / jog.send_rate_hz, 0.1)
        self._jogs_per_s = 2 * jog.send_rate_hz  # twice the page's rate: slack for bursts
        self.jogs_forwarded = 0
        self.assists_forwarded = 0  # arm_assist enables sent for a page holding the assist
        self.jog_ends = 0
        self.arm_stops = 0
        self.episode_marks = 0  # marks the node recorded (operator/episode_mark)

    async def jog_watchdog(self, page: Page) -> None:
        """Stop the arm when a jogging page goes quiet (a hung tab keeps its socket open)."""
        period = self._jog_watchdog_s / 4
        while True:
            await asyncio.sleep(period)
            if page.jogging and time.monotonic() - page.last_jog > self._jog_watchdog_s:
                self.end_jog(page, "page stopped sending jogs")

    def end_jog(self, page: Page, why: str) -> None:
        """The page's jog is over: the arm stops, and nothing is latched."""
        page.jogging = False
        self.node.send_command("arm_jog_end")
        self.jog_ends += 1
        log.info("dashboard: arm_jog_end (%s)", why)

    def stop_arm(self, page: Page) -> None:
        """STOP pressed on the page: latched on the robot, whoever else is jogging."""
        page.jogging = False
        self.node.send_command("arm_stop")
        self.arm_stops += 1
        log.warning("dashboard: STOP (arm_stop) from a page: latched on the robot until a resume")

    def resume_refusal(self) -> str | None:
        """Why the robot would refuse our ``arm_resume``, as far as its newest heartbeat tells."""
        control = (self._latest() or {}).get("control")
        if control is None or control["ours"]:  # unsigned: the one operator holds the arm
            return None
        if control["holder"] is None:
            return "only the lease holder may resume the arm, and nobody holds it: ask for control"
        return f"only the lease holder may resume the arm: {control['holder']}… holds it, not you"

    def on_message(self, raw: str | bytes, page: Page) -> dict[str, Any] | None:
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
            self.stop_arm(page)
            return {"type": "ack", "ok": True, "action": action}
        if action == "arm_jog_end":  # nor is the end of a jog
            self.end_jog(page, "released on the page")
            return {"type": "ack", "ok": True, "action": action}
        if action == "arm_jog":
            return self.on_jog(msg, page, now, delay_ms)
        if action == "arm_assist":
            return self.on_assist(page, now, delay_ms)
        if action == "episode_mark":
            return self.on_episode_mark(msg, page, now)
        sent_at = page.sent_at
        sent_at[:] = [t for t in sent_at if now - t < 1.0]
        if len(sent_at) >= COMMANDS_PER_S:
            return {"type": "ack", "ok": False, "action": action, "error": "too many commands"}
        if action == "arm_resume":
            refusal = self.resume_refusal()
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

    def on_episode_mark(self, msg: dict[str, Any], page: Page, now: float) -> dict[str, Any]:
        """The operator's mark on the episode in progress, recorded by the node (not sent).

        It shares the page's command budget, so a stuck key cannot flood the
        recording; refused with a reason when the node does not record.
        """
        from common.recording.episode_marks import check_mark

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

    def on_assist(self, page: Page, now: float, age_ms: float) -> dict[str, Any] | None:
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

    def on_jog(
        self, msg: dict[str, Any], page: Page, now: float, age_ms: float
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
                self.end_jog(page, "zero jog")
            return None
        self.node.send_command("arm_jog", velocity=twist, age_ms=age_ms)
        page.jogging, page.last_jog = True, now
        self.jogs_forwarded += 1
        return None


def cap_twist(velocity: list[float], max_linear: float, max_angular: float) -> tuple[float, ...]:
    """Scale the linear and angular parts (direction kept) to the operator's caps."""
    out = [float(v) for v in velocity]
    for part, cap in ((slice(0, 3), max_linear), (slice(3, 6), max_angular)):
        norm = math.sqrt(sum(v * v for v in out[part]))
        if norm > cap:
            out[part] = [v * cap / norm for v in out[part]]
    return tuple(out)
