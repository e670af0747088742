"""What ``deepxpalm topic`` counts, per robot and topic: rates, gaps, losses, sessions, signers.

Rates are per second of the robot's own clock (the messages' send times), so
they do not bend when the reader runs late; the gaps between receive times
show the path's jitter and the reader's stalls. The refusals a robot
reports are its heartbeat's counters named ``*refused*`` or ``*rejected*``.
"""

from __future__ import annotations

import collections
import dataclasses
from collections import Counter
from typing import Any

from common.clocks.clock import now_ns
from common.wire.link_stats import SEQ_RESTART_GAP
from deploy.wire_tap import Received

#: a heartbeat counter with one of these in its name is a refusal the robot reports
REFUSAL_WORDS = ("refused", "rejected")
#: the rates and gaps leave out what arrived in this long after the first message: a process
#: that has just started reads its first messages late (its first decodes load code; a loaded
#: machine schedules it late), and their receive times come bunched
WARM_UP_S = 0.5


@dataclasses.dataclass
class Arrival:
    t_recv_ns: int
    seq: int
    t_send_ns: int
    session: int | None


class TopicWatch:
    """One robot's one topic: arrivals in the window, and totals since the start."""

    def __init__(self, window_ns: int | None) -> None:
        self.window_ns = window_ns
        self.recent: collections.deque[Arrival] = collections.deque()
        self.count = 0
        self.bytes = 0
        self.lost = 0
        self.sessions: Counter[int | None] = Counter()
        self.signers: Counter[bytes | None] = Counter()
        self._last_seq: dict[int | None, int] = {}

    def add(self, got: Received, timed: bool = True) -> None:
        """``timed``: the arrival counts toward the rates (not during the tap's warm-up)."""
        msg = got.msg
        self.count += 1
        self.bytes += got.size
        self.sessions[msg.session] += 1
        self.signers[msg.signer] += 1
        last = self._last_seq.get(msg.session)
        self._last_seq[msg.session] = msg.seq
        if last is not None and 1 < msg.seq - last <= SEQ_RESTART_GAP:
            self.lost += msg.seq - last - 1
        if timed:
            self.recent.append(Arrival(got.t_recv_ns, msg.seq, msg.t_send_ns, msg.session))

    def trim(self, now: int) -> None:
        if self.window_ns is None:
            return
        while self.recent and now - self.recent[0].t_recv_ns > self.window_ns:
            self.recent.popleft()

    def rates(self) -> dict[str, float | None]:
        """Over the window: the rates (the newest run's messages) and the receive gaps.

        ``rate_hz``: the messages that arrived, over the span of their send times (the
        sender's clock); ``sent_hz``: the messages sent, their seq span over the same;
        ``seq_first``/``seq_last``: that span's ends, to find it in the sender's log. Timed
        by the sender's clock, neither bends when this process is late to read (a loaded
        machine ran it late, and the receive times of what waited came bunched: a rate over
        receive times read 15 % high, or twice the rate after a stall). What this process
        and the path did to the timing shows in the receive gaps.
        """
        out: dict[str, float | None] = {
            "rate_hz": None,
            "sent_hz": None,
            "seq_first": None,
            "seq_last": None,
            "gap_min_ms": None,
            "gap_max_ms": None,
        }
        recent = self.recent
        if len(recent) < 2:
            return out
        gaps = [b.t_recv_ns - a.t_recv_ns for a, b in zip(recent, list(recent)[1:], strict=False)]
        out["gap_min_ms"] = min(gaps) / 1e6
        out["gap_max_ms"] = max(gaps) / 1e6
        # the newest run's messages only: a restarted robot counts from 1 again
        run = [a for a in recent if a.session == recent[-1].session]
        span = max(a.t_send_ns for a in run) - min(a.t_send_ns for a in run)
        first, last = min(a.seq for a in run), max(a.seq for a in run)
        if len(run) >= 2 and span > 0:
            out["rate_hz"] = (len(run) - 1) * 1e9 / span
            out["sent_hz"] = (last - first) * 1e9 / span
            out["seq_first"], out["seq_last"] = first, last
        return out


class RobotWatch:
    """One robot: its topics, and the refusals its heartbeats report."""

    def __init__(self, window_ns: int | None) -> None:
        self.window_ns = window_ns
        self.topics: dict[str, TopicWatch] = {}
        self.refusals_first: dict[str, float] = {}
        self.refusals: dict[str, float] = {}

    def add(self, got: Received, timed: bool = True) -> None:
        watch = self.topics.get(got.topic)
        if watch is None:
            watch = self.topics[got.topic] = TopicWatch(self.window_ns)
        watch.add(got, timed)
        stats = getattr(got.msg, "stats", None)
        if got.topic == "heartbeat" and stats:
            for key, value in stats.items():
                if any(word in key for word in REFUSAL_WORDS):
                    self.refusals_first.setdefault(key, value)
                    self.refusals[key] = value


class Watch:
    """Everything read, per robot and topic."""

    def __init__(self, window_s: float | None, robot_key: bytes | None = None) -> None:
        self.window_ns = None if window_s is None else round(window_s * 1e9)
        self.robot_key = robot_key
        self.robots: dict[bytes, RobotWatch] = {}
        self.t_start_ns = now_ns()
        self.messages = 0
        #: arrivals before this count, but are not timed (``WARM_UP_S``)
        self.timed_from_ns: int | None = None

    def add(self, got: Received) -> None:
        robot = self.robots.get(got.robot)
        if robot is None:
            robot = self.robots[got.robot] = RobotWatch(self.window_ns)
        if self.timed_from_ns is None:
            self.timed_from_ns = got.t_recv_ns + round(WARM_UP_S * 1e9)
        robot.add(got, got.t_recv_ns >= self.timed_from_ns)
        self.messages += 1

    def signer_name(self, signer: bytes | None) -> str:
        """``unsigned``, ``robot key`` (the one ``--robot-key`` names) or the key's first digits."""
        if signer is None:
            return "unsigned"
        if self.robot_key is not None:
            if signer == self.robot_key:
                return "robot key"
            return f"key {signer.hex()[:16]} (NOT the robot's)"
        return f"key {signer.hex()[:16]}"

    def report(self, topics: tuple[str, ...], rejected: Counter[str]) -> dict[str, Any]:
        now = now_ns()
        robots: dict[str, Any] = {}
        for name, robot in sorted(self.robots.items()):
            per_topic: dict[str, Any] = {}
            for topic in topics:
                watch = robot.topics.get(topic)
                if watch is None:
                    per_topic[topic] = {"count": 0}
                    continue
                watch.trim(now)
                per_topic[topic] = {
                    "count": watch.count,
                    "in_window": len(watch.recent),
                    **watch.rates(),
                    "lost": watch.lost,
                    "bytes_mean": round(watch.bytes / watch.count, 1),
                    "sessions": {_session(s): n for s, n in watch.sessions.items()},
                    "signers": {self.signer_name(k): n for k, n in watch.signers.items()},
                }
            robots[name.decode("ascii")] = {
                "topics": per_topic,
                "refusals": dict(sorted(robot.refusals.items())),
                "refusals_while_watching": {
                    k: v - robot.refusals_first[k]
                    for k, v in sorted(robot.refusals.items())
                    if v != robot.refusals_first[k]
                },
            }
        return {
            "elapsed_s": round((now - self.t_start_ns) / 1e9, 3),
            "window_s": None if self.window_ns is None else self.window_ns / 1e9,
            "robots": robots,
            "rejected": dict(rejected),
        }


def _session(session: int | None) -> str:
    return "none" if session is None else f"{session:016x}"
