"""What the robot says besides stimuli: heartbeats, its stats, and raw frames for display.

A heartbeat carries the link state, the clock echo the operator's offset
filter needs (round robin over the roster's operators heard lately), the
last stimulus's seq (so a lost change is noticed), the lease holder and
the node's stats, cut to what the protocol allows.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable

from common.clocks.clock import Periodic
from common.fabric.link import HEARTBEAT_SPACING_MS
from common.keys.curve import Authenticator
from common.logs import BurstLog
from common.tactile.stimulus import sanitize_frame
from common.wire.codec import MAX_STATS, name_prefix
from common.wire.messages import Heartbeat, Stimulus, TactileFrame
from common.wire.transport import Sender
from robot_side.node.command_desk import CommandDesk
from robot_side.node.config import RobotLinkConfig
from robot_side.node.frame_pipeline import FramePipeline
from robot_side.node.workers import DeviceWorkers
from robot_side.tactile.base import TactileSample
from robot_side.video.link_signalling import LinkSignalling

log = logging.getLogger(__name__)


class HeartbeatSchedule:
    """When heartbeats go out: on a fixed grid (the rate exact), never more than a period apart.

    A heartbeat may go out up to ``early_s`` before its deadline with a
    frame's work (``Periodic``), and then the next one at its own deadline
    would leave a period plus ``early_s`` between the two: the loop wakes for
    the next one a period after the last instead, which always falls inside
    that one's early window, so the rate stays exactly ``hz``. A heartbeat sent
    off the grid (``Telemetry.announce``: a lease or latch change) is one
    more and moves no deadline, or the next would come up to two periods later.

    No two heartbeats go out closer than ``spacing_s`` (on the fabric: the
    router's rate gate drops the newer of two closer ones, and the newer is
    the one that announces a change); one due sooner waits for it.
    """

    def __init__(self, hz: float, early_s: float, spacing_s: float = 0.0) -> None:
        self._grid = Periodic(hz, early_s)
        self._last_ns: int | None = None  # the last heartbeat on the grid
        self._spacing_ns = round(spacing_s * 1e9)
        self._earliest_ns = 0  # the next heartbeat, on the grid or not, not before this

    @classmethod
    def of_link(cls, link_cfg: RobotLinkConfig) -> HeartbeatSchedule:
        """The schedule the link's config sets: its rate (or its mode's), its early window,
        and on the fabric the spacing its router's rate gate needs."""
        spacing_ms = HEARTBEAT_SPACING_MS if link_cfg.mode == "fabric" else 0.0
        return cls(link_cfg.heartbeat_rate_hz, link_cfg.heartbeat_early_ms / 1e3, spacing_ms / 1e3)

    @property
    def deadline_ns(self) -> int:
        """The latest time the next heartbeat may go out: the loop wakes for it then."""
        grid = self._grid.deadline_ns
        if self._last_ns is not None:
            grid = min(grid, self._last_ns + self._grid.period_ns)
        return max(grid, self._earliest_ns)

    def wake_ns(self, announce: bool) -> int:
        """When the loop wakes for the next heartbeat; ``announce``: one is wanted at once."""
        return self._earliest_ns if announce else self.deadline_ns

    def due(self, now: int) -> bool:
        """The heartbeat on the grid may go out now."""
        return now >= self._earliest_ns and self._grid.due(now)

    def may_announce(self, now: int) -> bool:
        """A heartbeat off the grid may go out now (far enough from the last one)."""
        return now >= self._earliest_ns

    def sent(self, now: int, on_grid: bool) -> None:
        """A heartbeat went out at ``now``: the one due on the grid, or one more."""
        if on_grid:
            self._grid.done(now)
            self._last_ns = now
        self._earliest_ns = now + self._spacing_ns


class Telemetry:
    """Heartbeats and display frames on the robot's stream."""

    def __init__(
        self,
        desk: CommandDesk,
        *,
        name: bytes,
        session: int,
        now: Callable[[], int],
        stats: Callable[[], dict[str, float]],
        counters: dict[str, int],
        stats_period_ms: float = 0.0,
    ) -> None:
        self.desk = desk
        #: heartbeats carry the counters at most this often (0: every one)
        self._stats_period_ns = round(stats_period_ms * 1e6)
        self._stats_due_ns = 0
        self.name = name
        self.session = session
        self.now = now
        self.stats = stats
        self.counters = counters
        self.pub: Sender | None = None  # set by the node once its link is open
        self.now_wanted = False  # a lease or latch change is announced at once, not in 50 ms
        self._hb_seq = 0
        self._frame_seq = 0
        self._echo_turn = 0  # round robin over the operators whose heartbeats we echo
        self._stats_cut = BurstLog(
            log, "heartbeat stats over the protocol's limit", level=logging.DEBUG
        )
        self._stats_turn = 0  # where the counters past the limit resume (``_heartbeat_stats``)

    def announce(self) -> None:
        """Send a heartbeat at the next loop turn."""
        self.now_wanted = True

    def send_heartbeat(
        self, state: str, last: Stimulus | None, last_capture_ns: int | None
    ) -> None:
        """``last``: the last change sent, which the keyframes since repeat (``stimulus_seq``)."""
        self.now_wanted = False
        self._hb_seq += 1
        desk, lease = self.desk, self.desk.lease
        echo_send, echo_recv = desk.clock.echo_fields()
        echo_signer = holder = pending = None
        if lease is not None:
            echo_signer, echo_send, echo_recv = self._next_echo()
            holder, pending = lease.holder, lease.pending
        self.pub.send(
            Heartbeat(
                seq=self._hb_seq,
                t_send_ns=self.now(),
                node="robot",
                state=state,
                echo_t_send_ns=echo_send,
                echo_t_recv_ns=echo_recv,
                stimulus_seq=last.seq if last else None,
                t_capture_ns=last_capture_ns if last else None,
                stats=self._heartbeat_stats(),
                echo_signer=echo_signer,
                lease_holder=holder,
                lease_pending=pending,
                session=self.session,
            )
        )

    def _next_echo(self) -> tuple[bytes | None, int | None, int | None]:
        """(key, echo fields) of the next operator heard in the last second, round robin.

        One heartbeat echoes one operator; taking turns gives each of five
        operators four clock samples a second, which its offset filter needs.
        """
        now = self.now()
        peers = self.desk.lease.peers
        recent = [k for k, p in peers.items() if now - p.last_heard_ns < 1_000_000_000]
        if not recent:
            return None, None, None
        self._echo_turn = (self._echo_turn + 1) % len(recent)
        key = recent[self._echo_turn]
        echo_send, echo_recv = peers[key].clock.echo_fields()
        return key, echo_send, echo_recv

    def _heartbeat_stats(self) -> dict[str, float]:
        """``stats()``, cut to what a heartbeat may carry: the operator refuses a longer map.

        Between two periods of ``stats_period_ms``: only what an operator acts on
        (``state_stats``: the stop latch, the gripper's acknowledgement).
        """
        if self._stats_period_ns:
            now = self.now()
            if now < self._stats_due_ns:
                return state_stats(self.desk)  # not the whole counters: not computed either
            self._stats_due_ns = now + self._stats_period_ns
        stats = self.stats()
        if len(stats) <= MAX_STATS:
            return stats
        # in every one: what an operator acts on (the stop latch, the gripper's acknowledgement)
        # and the links' health (`deepxpalm doctor` reads it from one heartbeat); the other
        # counters take turns in the room left, so each is carried every few heartbeats and an
        # operator, which keeps the newest value of each, sees them all (cut in name order
        # instead, the last few, `video_signals_replayed` and `wakeups` among them, were never
        # sent)
        fixed = [k for k in STATE_KEYS if k in stats]
        fixed += sorted(k for k in stats if k.startswith("link_"))[: MAX_STATS - len(fixed)]
        rest = sorted(stats.keys() - set(fixed))
        room = MAX_STATS - len(fixed)
        start = self._stats_turn % len(rest) if rest else 0
        turn = (rest[start:] + rest[:start])[:room]
        self._stats_turn = start + room
        self._stats_cut(f"{len(stats)} counters: {MAX_STATS} a heartbeat, the rest in turns")
        return {k: stats[k] for k in (*fixed, *turn)}

    def send_frame(self, sample: TactileSample) -> None:
        """The raw frame, for the dashboard's display; not even encoded when nobody wants it."""
        if not self.pub.wanted(name_prefix(TactileFrame.TOPIC, self.name)):
            self.counters["frames_unwanted"] += 1
            return
        self._frame_seq += 1
        self.pub.send(
            TactileFrame(
                seq=self._frame_seq,
                t_send_ns=self.now(),
                t_capture_ns=sample.t_capture_ns,
                frame_seq=sample.seq,
                frame=sanitize_frame(sample.frame),
                session=self.session,
            )
        )


#: across the fabric a heartbeat carries the counters once a second (one datagram otherwise)
FABRIC_STATS_PERIOD_MS = 1000.0


#: the state an operator acts on, in every heartbeat (``state_stats``)
STATE_KEYS = ("arm_stop_latched", "gripper_command_seq", "gripper_command_session")


def state_stats(desk: CommandDesk) -> dict[str, float]:
    """What every heartbeat carries whatever the counters' period: the state an operator acts
    on (the stop latch; the newest gripper command acted on, which confirms the operator's)."""
    latched, seq, session = STATE_KEYS
    out = {latched: float(desk.stop_latch.latched)}
    ack = desk.handover.gripper_ack
    if ack is not None:
        out[seq], out[session] = ack
    return out


#: raw frames a second for the operator's heatmaps: on a direct link, and on the fabric. None
#: there by default: a frame is a datagram of about 1.1 kB, nearly half of what QUIC's smallest
#: congestion window lets through a round trip, and the stimuli behind it waited a round trip
#: (bad_day over the fabric: 3-11 palm lift-offs in 30 s with frames at 2 or 5 Hz, 1-3 without)
DIRECT_FRAME_DISPLAY_HZ, FABRIC_FRAME_DISPLAY_HZ = 15.0, 0.0


def frame_display_rate_hz(link: RobotLinkConfig) -> float:
    """The config's display frame rate, or the link mode's default."""
    if link.frame_display_rate_hz is not None:
        return link.frame_display_rate_hz
    return FABRIC_FRAME_DISPLAY_HZ if link.mode == "fabric" else DIRECT_FRAME_DISPLAY_HZ


def stats_period_ms(link: RobotLinkConfig) -> float:
    """How often heartbeats carry the counters: the config's, or the link mode's default."""
    if link.heartbeat_stats_period_ms is not None:
        return max(0.0, link.heartbeat_stats_period_ms)
    return FABRIC_STATS_PERIOD_MS if link.mode == "fabric" else 0.0


def node_stats(
    counters: Counter[str],
    workers: DeviceWorkers,
    video: LinkSignalling | None,
    auth: Authenticator | None,
    pipeline: FramePipeline,
    desk: CommandDesk,
) -> dict[str, float]:
    """What the heartbeat's stats and ``RobotNode.stats()`` say: every part's counters."""
    out = {k: float(v) for k, v in counters.items()}
    for k, v in workers.stats().items():  # counted on the workers' own threads
        out[k] = out.get(k, 0.0) + v
    if video is not None:
        out.update((k, float(v)) for k, v in video.counters.items())
    if auth is not None and auth.refused:
        out["curve_refused"] = float(auth.refused)
    out.update(workers.availability())
    if pipeline.first_seq is not None:
        out["frames_captured"] = float(pipeline.last_seq - pipeline.first_seq + 1)
    out.update(workers.arm_readings())  # the arm worker's latest reading, for the dashboard
    if desk.assist is not None:
        out.update(desk.assist.stats())
    out.update(state_stats(desk))
    return out
