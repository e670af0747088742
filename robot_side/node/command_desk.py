"""Every operator message the robot reads, admitted in one place and acted on through a table.

``CommandDesk.admit`` is the one admission path, signed or not (peers.py:
an unsigned link is a roster of one operator who always holds control):

1. whose message is it: a key of the roster, or the one operator;
2. once, in order and of this robot run: every kind passes the sender's
   replay window (command_gate.py): a replayed heartbeat or video signal is
   refused as a replayed command is;
3. a heartbeat syncs that sender's clock and keeps its deadman alive; a
   video signal goes to the video desk; a command must be fresh by the
   sender's own clock (command_gate.py). An ``arm_stop`` the window cannot
   yet believe stops the arm now and latches once its sender proves live
   (``PENDING``: the gate's trade-off);
4. a lease action changes who holds control (lease.py), and stops there;
5. the stop latch's word (stop_latch.py): only the holder moves the arm,
   and nothing moves it while a stop is latched;
6. an ``arm_assist`` (the holder's enable) goes to the assist (assist.py),
   and any other command from the holder ends an assist in progress;
7. the newest admitted command of each device wins the batch; it goes to
   its device's worker through ``DEVICE_CALLS`` (device_calls.py).

The assist's own commands (``Handover.act_for_holder``, handover.py) take
steps 5 and 7: the same stop latch, device calls, clipping and recording as
the holder's. The desk owns the assist and tells it what it admitted; the
assist never calls the desk (it is handed the hand-over's callables).

Whatever arrives, from a dashboard page, a gamepad, a script or the API,
passes the same clipping (the arm driver's), deadman and stop latch.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable

from common.clocks.clock_sync import ClockSync
from common.errors import ConfigError
from common.keys.roster import Roster, check_replacement, load_roster
from common.logs import BurstLog
from common.wire.messages import LEASE_ACTIONS, Command, Heartbeat, Message, VideoSignal
from robot_side.node.assist import Assist
from robot_side.node.commands.command_gate import PENDING, CommandGate, RobotRun
from robot_side.node.commands.lease import ControlLease, Peer
from robot_side.node.commands.stop_latch import REFUSALS, StopLatch
from robot_side.node.config import RobotLinkConfig
from robot_side.node.device_calls import DEVICE_CALLS
from robot_side.node.handover import Handover
from robot_side.node.peers import OnePeer, RosterPeers
from robot_side.node.pending_stops import PendingStops

log = logging.getLogger(__name__)

#: the newest admitted command of each device in a batch, with its send time on our clock
Newest = dict[str, tuple[Command, int | None]]


class CommandDesk:
    """Admission, the lease and the stop latch, and the hand-over to the device workers."""

    def __init__(
        self,
        link_cfg: RobotLinkConfig,
        handover: Handover,
        assist: Assist | None,
        *,
        counters: Counter[str],
        now: Callable[[], int],
        on_video: Callable[[VideoSignal, bytes | None], None],
        announce: Callable[[], None],
        session: int = 0,
    ) -> None:
        """``handover``: the stop latch and the devices (handover.py);
        ``assist``: the reflex an ``arm_assist`` holds (None: refused);
        ``announce`` asks for a heartbeat at once (a lease or latch change);
        ``session``: this robot run's boot id, which operators echo to prove a message is of it."""
        self.link_cfg = link_cfg
        self.counters = counters
        self.on_video = on_video
        self.announce = announce
        max_age_ns = round(link_cfg.max_command_age_ms * 1e6)
        #: this run: what an operator's message must echo, and when it started
        self.run = RobotRun(session, now())
        #: the stop latch, the device workers' queue and the robot/command recording
        self.handover = handover
        self.assist = assist
        #: arm_stops that wait for their sender's proof (pending_stops.py)
        self.pending_stops = PendingStops(
            self.handover, self.run, counters=counters, announce=announce
        )
        self._refused_log = BurstLog(log, "operator message refused (replay window)")
        self._malformed_stop_log = BurstLog(log, "arm_stop with malformed fields, acted on")
        #: the one operator's clock on an unsigned link (each roster key has its own)
        self.clock = ClockSync()
        #: the roster in force (a reload that would lock everyone out keeps it)
        self.roster: Roster | None = None
        #: with a roster: signed commands, obeyed only from the lease holder (lease.py)
        self.lease: ControlLease | None = None
        self.peers: OnePeer | RosterPeers = OnePeer(self.clock, max_age_ns)
        if link_cfg.roster_file is not None:
            roster = self.roster = load_roster(link_cfg.roster_file)
            self.lease = ControlLease(
                roster.by_signing_key(), max_age_ns, round(link_cfg.lease_request_timeout_ms * 1e6)
            )
            self.peers = RosterPeers(self.lease)
        elif link_cfg.mode == "fabric":
            raise ConfigError(
                f"robot link.mode = {link_cfg.mode!r} needs link.roster_file: across sites only "
                "signed commands from the lease holder may move the arm (docs/security.md)"
            )
        self._lease_changes_seen = 0

    @property
    def stop_latch(self) -> StopLatch:
        """An operator's arm_stop holds the arm until the holder's arm_resume (stop_latch.py)."""
        return self.handover.stop_latch

    @property
    def gate(self) -> CommandGate:
        """The gate whose newest fresh message the deadman counts from (the holder's)."""
        return self.peers.holder_gate

    def take(self, batch: list[tuple[Message, int]], now: int) -> None:
        """Admit a batch; hand the newest admitted command of each device to its worker."""
        newest: Newest = {}
        for msg, t_recv in batch:
            self.admit(msg, t_recv, now, newest)
        if self.pending_stops:  # after the batch: it may hold the proof
            self.pending_stops.judge(now)
        if self.lease is not None:
            timed_out = self.lease.tick(now)
            if timed_out is not None:
                self.counters[timed_out] += 1
            self._follow_lease(now, newest)
        for device, (cmd, sent) in newest.items():
            self.handover.dispatch(device, cmd, sent)

    def admit(self, msg: Message, t_recv: int, now: int, newest: Newest) -> None:
        """The one admission of an operator message, signed or not (the module's steps 1-6)."""
        found = self.peers.find(msg)
        if isinstance(found, str):
            self.counters[found] += 1
            return
        key, peer = found
        if isinstance(msg, (Heartbeat, VideoSignal)):
            refusal = peer.gate.admit_signal(msg, self.run)
            if refusal is not None:
                self._refused(refusal, msg, peer)
                return
        peer.last_heard_ns = now
        if isinstance(msg, Heartbeat):
            peer.clock.on_heartbeat(msg.t_send_ns, msg.echo_t_send_ns, msg.echo_t_recv_ns, t_recv)
            peer.gate.heard(msg.t_send_ns, t_recv, now)
            return
        if isinstance(msg, VideoSignal):  # any role may watch: the roster vouched for it
            self.on_video(msg, key)
            return
        if not isinstance(msg, Command):
            self.counters["messages_unexpected"] += 1
            return
        self.counters["commands_received"] += 1
        if msg.defects:
            self.counters["arm_stops_malformed"] += 1
            self._malformed_stop_log(f"from {peer.entry.name}: {'; '.join(msg.defects)}")
        refusal, sent = peer.gate.admit(msg, t_recv, now, self.run)
        if refusal == PENDING:
            if self.pending_stops.pend(key, peer, msg, t_recv, self.peers.holds(key)):
                if self.assist is not None:
                    self.assist.end(f"arm_stop from {peer.entry.name}")
                self._newest(newest, "arm", msg, None)
            return
        if refusal is not None:
            self._refused(refusal, msg, peer)
            self.handover.record(msg, f"refused: {refusal}")
            return
        if msg.action in LEASE_ACTIONS:
            outcome = self.peers.lease_action(key, msg, now)
            self.counters[outcome] += 1
            self.handover.record(msg, outcome)
            return
        holder, who = self.peers.holds(key), peer.entry
        if self.assist is not None and msg.action == "arm_stop":
            self.assist.end(f"arm_stop from {who.name}")  # anyone's stop the latch obeys
        if not self._latch_lets(msg, holder, who.role, who.name, now):
            return
        if msg.action == "arm_assist":
            self._hold_assist(msg, sent if sent is not None else t_recv, now)
            return
        if self.assist is not None:
            self.assist.end(f"the holder's own {msg.action}")
            if msg.action.startswith("gripper_"):
                self.assist.gripper_taken()
        call = DEVICE_CALLS.get(msg.action)
        if call is None:  # the codec admits no other action; should one be added, say so
            self.counters["messages_unexpected"] += 1
            return
        self._newest(newest, call.device, msg, sent)

    def _newest(self, newest: Newest, device: str, msg: Command, sent: int | None) -> None:
        """Newest only: an older wish of the same device in the batch is never acted on."""
        older = newest.get(device)
        if older is not None:
            self.counters["commands_superseded"] += 1
            self.handover.record(older[0], "superseded")
        newest[device] = (msg, sent)

    def _refused(self, refusal: str, msg: Message, peer: Peer) -> None:
        self.counters[refusal] += 1
        # routine: an operator's first messages of a run, before it has heard the robot's
        if refusal not in ("commands_unsynced", "commands_stale", "messages_unproven"):
            self._refused_log(
                f"{refusal}: {type(msg).__name__} from {peer.entry.name}, boot "
                f"{msg.session or 0:016x}, seq {msg.seq}"
            )

    def _hold_assist(self, msg: Command, enable_ns: int, now: int) -> None:
        refusal = "assist_refused_none" if self.assist is None else self.assist.hold(enable_ns, now)
        if refusal is not None:
            self.counters[refusal] += 1
            self.handover.record(msg, f"refused: {refusal}")
            return
        self.counters["assist_enables"] += 1

    def _latch_lets(self, msg: Command, holder: bool, role: str, who: str, now: int) -> bool:
        """The stop latch's word on an admitted command: True to act on it on the device.

        A refusal is counted and recorded with its reason; an ``arm_resume``
        is used up here (it moves nothing), an ``arm_stop`` latches and goes
        on to stop the arm.
        """
        latch = self.stop_latch
        refusal = latch.judge(msg.action, holder, role)
        if refusal is not None:
            self.counters[refusal] += 1
            self.handover.record(msg, f"refused: {REFUSALS[refusal]}")
            return False
        if msg.action == "arm_resume":
            self.pending_stops.release(who)
        if msg.action in ("arm_stop", "arm_resume"):
            if latch.apply(msg.action, who, now):
                self.announce()  # every operator sees the latch change at once
            self.counters["arm_stops_latched" if msg.action == "arm_stop" else "arm_resumes"] += 1
        if msg.action == "arm_resume":
            self.handover.record(msg, "applied")
            return False
        return True

    # -------------------------------------------------------------- the lease
    def holder_silent(self, now: int) -> None:
        """The deadman tripped: the holder's lease expires (a waiting requester takes over)."""
        lease = self.lease
        if lease is not None and lease.holder is not None:
            self.counters["lease_expired"] += 1
            lease.expire(now)
            self._follow_lease(now, {})
        if self.assist is not None:
            self.assist.end("operator silent")

    def reload_roster(self, now: int) -> bool:
        """Read ``link.roster_file`` again; a broken file keeps the roster in force, and so
        does one that would remove every controller or every robot (``check_replacement``).

        A key added may act from its next message; a key removed is ignored
        from now on, and if it held the lease the arm stops (as at any change
        of holder).
        """
        path = self.link_cfg.roster_file
        if self.lease is None or path is None:
            log.warning("roster reload asked, but this robot has no link.roster_file")
            return False
        try:
            roster = load_roster(path)
            if self.roster is not None:
                check_replacement(self.roster, roster, path)
        except ConfigError as e:
            self.counters["roster_reloads_failed"] += 1
            log.error("roster reload failed, the roster in force stays: %s", e)
            return False
        self.roster = roster
        changes = self.lease.replace_roster(roster.by_signing_key())
        self.counters["roster_reloads"] += 1
        log.info(
            "roster %s reloaded: %d operator keys; %s",
            path,
            len(self.lease.operators),
            "; ".join(changes) or "nothing changed",
        )
        self._follow_lease(now, {})
        return True

    def _follow_lease(self, now: int, newest: Newest) -> None:
        """After the holder changed: the deadman follows the new holder, the arm stops once.

        Stopping at a hand-over means the new holder starts from rest, never
        from the old holder's last jog; its own commands in this batch still go.
        """
        lease = self.lease
        if lease.changes == self._lease_changes_seen:
            return
        self._lease_changes_seen = lease.changes
        self.announce()
        why = f"control lease now {lease.holder_name() or 'nobody'}'s"
        if self.assist is not None:
            self.assist.end(why)
        if not any(cmd.action == "arm_jog" for cmd, _ in newest.values()):
            self.handover.workers.stop_devices(why)
