"""The command outbox: what the operator sends the robot, queued from any thread, sent by the loop.

- a jog (and the assist's enable, held like one) goes out only while the
  robot's telemetry is fresh (``RobotHeard.sees_robot``): with it stale we
  cannot see what we steer, whichever half of the link failed, so it is
  dropped and the robot's deadman stops the arm; one that waited longer
  than ``jog_max_age_ms`` (a busy PC) is dropped too, the hand may have let
  go since. Stops, gripper and lease commands always go;
- a gripper command is one-shot: lost, or refused as stale after a stall on
  the link, the gripper would silently not move. The robot's heartbeat
  names the newest gripper command it acted on (``gripper_command_seq``,
  ``gripper_command_session``); until it names ours, it is sent again as a
  new command (fresh seq and send time) every ``gripper_confirm_ms``,
  ``gripper_resends`` times at most;
- an ``arm_stop`` is sent again as a new command every ``stop_resend_ms``
  until the robot's heartbeat shows its stop latch set (``arm_stop_latched``,
  in every heartbeat), for ``stop_resend_for_ms`` at most, and never after
  this operator sent another arm command (a resume must not be undone by a
  late copy of the stop before it);
- a video signal (a WebRTC offer or bye) is held until the robot is known to
  hear us, then sent in order (``release_held_signals``).

Every message carries this run's session and echoes the robot's.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import math
import os
import queue
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

from common.clocks.clock_sync import ClockSync
from common.logs import BurstLog
from common.wire.messages import SESSION_LOW_MASK, Command, VideoSignal
from common.wire.transport import Sender
from operator_side.node.arrivals import RobotHeard
from operator_side.node.config import OperatorLinkConfig
from operator_side.node.operator_channels import OperatorChannels

log = logging.getLogger(__name__)

#: longest a video signal waits for the robot to show it hears us before it goes anyway
VIDEO_HOLD_NS = 3_000_000_000


@dataclass
class PendingGripper:
    """The newest gripper command, until the robot's heartbeat confirms it."""

    action: str
    grip_level: int | None
    seq: int
    deadline_ns: int
    resends: int


@dataclass
class PendingStop:
    """An arm_stop the robot has not yet shown latched: when it was first sent, when next."""

    since_ns: int
    next_ns: int


class Outbox:
    """Commands and video signals from any thread to the robot, on the loop's thread."""

    def __init__(
        self,
        link_cfg: OperatorLinkConfig,
        heard: RobotHeard,
        clock: ClockSync,
        pub: Callable[[], Sender],
        *,
        session: int,
        counters: Counter[str],
        now: Callable[[], int],
        recording: OperatorChannels,
    ) -> None:
        """``pub``: the publisher in use (the node opens it again after a silence);
        ``session``: this run's boot id."""
        self.link_cfg = link_cfg
        self.heard = heard
        self.clock = clock
        self.pub = pub
        self.session = session
        self.counters = counters
        self.now = now
        self.recording = recording
        # each with when the operator issued it (our clock): a jog that waited too long is dropped
        self._queue: queue.SimpleQueue[tuple[int, Command | VideoSignal]] = queue.SimpleQueue()
        #: (queued at, signal): video signals held until the robot is known to hear us
        self.held_signals: collections.deque[tuple[int, VideoSignal]] = collections.deque()
        self.wake_r, self._wake_w = os.pipe()  # a queued command wakes a sleeping loop
        os.set_blocking(self.wake_r, False)
        os.set_blocking(self._wake_w, False)
        self._cmd_seq = 0
        self._vsig_seq = 0
        self.gripper_pending: PendingGripper | None = None
        self.stop_pending: PendingStop | None = None
        self._blind_log = BurstLog(log, "jog held: no fresh telemetry, we cannot see the arm")
        self._late_log = BurstLog(log, "jog dropped: it waited too long on this busy PC")

    # ------------------------------------------------------- any thread
    def put_command(self, cmd: Command, age_ms: float) -> None:
        """Queue a command issued ``age_ms`` ago; thread-safe."""
        issued = self.now() - round(max(age_ms, 0.0) * 1e6) if math.isfinite(age_ms) else 0
        self._queue.put((issued, cmd))
        self._wake(b"c")

    def put_video_signal(self, signal: VideoSignal) -> None:
        self._queue.put((self.now(), signal))
        self._wake(b"v")

    def _wake(self, why: bytes) -> None:
        with contextlib.suppress(BlockingIOError, OSError):
            os.write(self._wake_w, why)  # the loop may be asleep until a deadline

    # -------------------------------------------------------- the loop
    def drain_wake_pipe(self) -> None:
        with contextlib.suppress(BlockingIOError, OSError):
            os.read(self.wake_r, 4096)

    def flush(self, now: int) -> None:
        """Send what was queued; resend a gripper command nobody confirmed (the module's rules)."""
        while True:
            try:
                issued, cmd = self._queue.get_nowait()
            except queue.Empty:
                break
            if isinstance(cmd, VideoSignal):  # sent below, in order, once the robot hears us
                self.held_signals.append((now, cmd))
                continue
            if cmd.action in ("arm_jog", "arm_assist"):  # the assist is held like a jog
                if (now - issued) / 1e6 > self.link_cfg.jog_max_age_ms:
                    # the hand may have let go since: the robot's deadman stops the arm
                    self.counters["jogs_dropped_late"] += 1
                    self._late_log(f"{cmd.action}, {(now - issued) / 1e6:.0f} ms old")
                    continue
                if not self.heard.sees_robot(now):
                    self.counters["jogs_held_blind"] += 1
                    self._blind_log(cmd.action)
                    continue
            self._send_command(cmd, now, resends=0)
        self.release_held_signals(now)
        self._resend_gripper(now)
        self._resend_stop(now)

    def _resend_stop(self, now: int) -> None:
        pending = self.stop_pending
        if pending is None or now < pending.next_ns:
            return
        if (now - pending.since_ns) / 1e6 > self.link_cfg.stop_resend_for_ms:
            self.stop_pending = None
            self.counters["stops_unconfirmed"] += 1
            log.warning(
                "the robot never showed our STOP latched in %.0f ms: a recorder's key, or the "
                "link is down (the robot's deadman stops the arm then)",
                self.link_cfg.stop_resend_for_ms,
            )
            return
        self.counters["stops_resent"] += 1
        self._send_command(Command(seq=0, t_send_ns=0, action="arm_stop"), now, resends=1)
        pending.next_ns = now + round(self.link_cfg.stop_resend_ms * 1e6)

    def _resend_gripper(self, now: int) -> None:
        pending = self.gripper_pending
        if pending is None or now < pending.deadline_ns:
            return
        if pending.resends >= self.link_cfg.gripper_resends:
            self.gripper_pending = None
            self.counters["gripper_unconfirmed"] += 1
            log.warning(
                "the robot never confirmed %s (%d resends): not the lease holder, or the link "
                "is down",
                pending.action,
                pending.resends,
            )
            return
        self.counters["gripper_resent"] += 1
        again = Command(seq=0, t_send_ns=0, action=pending.action, grip_level=pending.grip_level)
        self._send_command(again, now, resends=pending.resends + 1)

    def release_held_signals(self, now: int) -> None:
        """Send the held video signals, in order, once the robot is known to hear us.

        An offer is sent once and answered once: one the link drops (the
        command link's subscription not yet through, a robot still starting)
        leaves the page waiting for its answer timeout. The robot echoing our
        heartbeat (the clock has a sample) shows the command link carries; a
        robot that never echoes gets the signals after ``VIDEO_HOLD_NS``.
        """
        held = self.held_signals
        if not held:
            return
        if not self.clock.is_synced:
            if now - held[0][0] < VIDEO_HOLD_NS:
                return
            log.warning("video signals sent unconfirmed: the robot has not echoed a heartbeat")
        while held:
            self._send_video_signal(held.popleft()[1])

    def _send_video_signal(self, cmd: VideoSignal) -> None:
        self._vsig_seq += 1
        cmd.seq, cmd.t_send_ns = self._vsig_seq, self.now()
        cmd.session, cmd.echo_session = self.session, self.heard.session
        self.pub().send(cmd)
        self.counters[f"video_{cmd.kind}s_sent"] += 1

    def _send_command(self, cmd: Command, now: int, resends: int) -> None:
        self._cmd_seq += 1
        cmd.seq, cmd.t_send_ns, cmd.session = self._cmd_seq, self.now(), self.session
        cmd.echo_session = self.heard.session
        data = self.pub().send(cmd)
        self.counters["commands_sent"] += 1
        self.recording.command(cmd.seq, cmd.t_send_ns, data)
        if cmd.action == "arm_stop":
            if resends == 0 and self.link_cfg.stop_resend_ms > 0:
                next_ns = now + round(self.link_cfg.stop_resend_ms * 1e6)
                self.stop_pending = PendingStop(now, next_ns)
        elif cmd.action.startswith("arm_"):
            self.stop_pending = None  # a resume (or a jog) after the stop: never re-stop after it
        if cmd.action.startswith("gripper"):
            deadline = now + round(self.link_cfg.gripper_confirm_ms * 1e6)
            self.gripper_pending = PendingGripper(
                cmd.action, cmd.grip_level, cmd.seq, deadline, resends
            )

    def on_robot_stats(self, stats: dict[str, float]) -> None:
        """A robot heartbeat's state: it may confirm our STOP and our gripper command."""
        if self.stop_pending is not None and stats.get("arm_stop_latched"):
            self.stop_pending = None
            self.counters["stops_confirmed"] += 1
        self.confirm_gripper(stats)

    def confirm_gripper(self, stats: dict[str, float]) -> None:
        """The robot's heartbeat names the newest gripper command it acted on."""
        pending = self.gripper_pending
        if pending is None:
            return
        if stats.get("gripper_command_session") != float(self.session & SESSION_LOW_MASK):
            return
        if stats.get("gripper_command_seq", -1.0) >= pending.seq:
            self.gripper_pending = None
            self.counters["gripper_confirmed"] += 1
