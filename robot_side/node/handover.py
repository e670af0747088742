"""The hand-over of an admitted command to its device's worker, and its one recording.

Every command that reaches a device, the holder's or the assist's, goes
through ``Handover.dispatch``: ``DEVICE_CALLS`` (device_calls.py) makes the
call, the device's worker runs it, and its outcome is written to
``robot/command`` once known. A refused command is recorded here too, with
its reason, so ``robot/command`` is written in one place.

The assist's commands come in through ``act_for_holder``: the stop latch
judges them as the lease holder's own (the assist acts only for the holder).
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable
from typing import Any

from common.errors import DeviceError
from common.recording.channels import Recorder
from common.wire.codec import DecodeError
from common.wire.messages import SESSION_LOW_MASK, Command
from robot_side.devices.device_worker import DeviceRequest
from robot_side.node.commands.stop_latch import REFUSALS, StopLatch
from robot_side.node.device_calls import DEFAULT_CLOSE_LEVEL, DEVICE_CALLS
from robot_side.node.workers import DeviceWorkers

log = logging.getLogger(__name__)


class Handover:
    """The stop latch, the device workers' queue and the ``robot/command`` recording."""

    def __init__(
        self,
        workers: DeviceWorkers,
        *,
        counters: Counter[str],
        now: Callable[[], int],
        recorder: Recorder | None,
    ) -> None:
        """``recorder`` None records nothing."""
        self.workers = workers
        self.counters = counters
        self.now = now
        self.recorder = recorder
        #: an operator's arm_stop holds the arm until the holder's arm_resume (stop_latch.py)
        self.stop_latch = StopLatch()
        #: (seq, low 32 bits of the session) of the newest gripper command handed to the gripper
        self.gripper_ack: tuple[float, float] | None = None
        #: the grip level of the newest gripper_close handed to the gripper (the assist's
        #: re-grasp closes at it: the level the fingers read is where they met the pipette)
        self.grip_level_commanded: int | None = None

    def act_for_holder(self, cmd: Command, sent_ns: int | None) -> bool:
        """A command the robot makes for the lease holder (the assist), on the holder's path.

        The stop latch judges it as the holder's own, ``DEVICE_CALLS`` carries
        it out (an arm velocity passes the arm driver's caps and box clipping,
        and ``sent_ns``, the holder's enable, starts the arm's jog deadman) and
        it is recorded in ``robot/command``. It never names itself in the
        heartbeat's gripper acknowledgement, which is the operator's own.
        False when refused.
        """
        refusal = self.stop_latch.judge(cmd.action, True)
        if refusal is not None:
            self.counters[refusal] += 1
            self.record(cmd, f"refused: {REFUSALS[refusal]}", by_assist=True)
            return False
        self.counters["assist_commands"] += 1
        self.dispatch(DEVICE_CALLS[cmd.action].device, cmd, sent_ns, by_assist=True)
        return True

    def dispatch(
        self, device: str, cmd: Command, sent_ns: int | None, *, by_assist: bool = False
    ) -> None:
        """Hand the command to its device's worker; a missing device refuses at once."""
        if device not in self.workers.workers:
            self.counters["commands_rejected"] += 1
            log.warning("command %s rejected: this scene has no %s", cmd.action, device)
            self.record(cmd, f"rejected: this scene has no {device}", by_assist=by_assist)
            return
        if device == "gripper" and not by_assist:
            # the heartbeat names it, so the operator can resend a gripper command we never saw
            self.gripper_ack = (float(cmd.seq), float((cmd.session or 0) & SESSION_LOW_MASK))
            if cmd.action == "gripper_close":
                self.grip_level_commanded = cmd.grip_level or DEFAULT_CLOSE_LEVEL
        call, args = DEVICE_CALLS[cmd.action].make(self.workers.device(device), cmd, sent_ns)
        self.workers.post(
            device, DeviceRequest(cmd.action, call, args, self._on_done(cmd, sent_ns, by_assist))
        )

    def _on_done(
        self, cmd: Command, sent_ns: int | None, by_assist: bool = False
    ) -> Callable[..., None]:
        def on_done(request: DeviceRequest, result: Any, error: BaseException | None) -> None:
            if error is None:
                outcome = "applied"
            elif isinstance(error, (DeviceError, ValueError, DecodeError)):
                log.warning("command %s rejected: %s", cmd.action, error)
                outcome = f"rejected: {error}"
            else:
                log.error("command %s failed: %r", cmd.action, error)
                outcome = f"failed: {error!r}"
            sent = result if cmd.action == "arm_jog" and error is None else None
            self.record(cmd, outcome, sent, sent_ns, by_assist=by_assist)

        return on_done

    def record(
        self,
        cmd: Command,
        outcome: str,
        sent: Any = None,
        sent_ns: int | None = None,
        *,
        by_assist: bool = False,
    ) -> None:
        """``t_sent_ns`` (the operator's send time on our clock) is when the arm's jog
        deadline started counting, which an exporter needs to end the jog where the arm did.
        The assist's commands say so (``by``: its seqs are its own, not an operator's)."""
        if self.recorder is None:
            return
        self.recorder.write(
            "robot/command",
            self.now(),
            ({"by": "assist"} if by_assist else {})
            | {
                "seq": cmd.seq,
                "action": cmd.action,
                "grip_level": cmd.grip_level,
                "velocity": list(cmd.velocity) if cmd.velocity else None,
                "sent_velocity": None if sent is None else [float(v) for v in sent],
                "t_sent_ns": sent_ns,
                "outcome": outcome,
            },
        )
