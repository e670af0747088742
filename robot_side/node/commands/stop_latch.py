"""STOP means stop: an operator's ``arm_stop`` latches on the robot until the holder resumes.

A stop that only ended the jog in flight did not stop anything for long: a
second dashboard page still holding its jog restarted the arm 33 ms later.
The latch lives on the robot because that is where every input path meets
(every page, gamepad, SpaceMouse, terminal key, script and API call ends as
a command here):

- ``arm_stop`` latches and stops the arm. It is obeyed from the lease holder
  and from any roster key whose role may stop (``STOP_ROLES``: controllers
  and observers; a recorder is a machine and presses nothing);
- while latched, every command that could set the arm moving
  (``MOVES_ARM``) is refused and counted (``commands_stop_latched``);
- only ``arm_resume`` from the lease holder (without a roster: the one
  operator) releases it. No jog, no ``arm_jog_end``, no lease hand-over and
  no roster reload does;
- ``arm_jog_end`` (a hold-to-move input let go) stops the arm and latches
  nothing: it ends one jog, it is not a STOP.

A stop whose sender has not yet proven it hears this robot run (command_gate.py,
``PENDING``) stops the arm at once and holds it as a latch would (``pending``)
while the proof is awaited; proven, it latches, refused, the hold ends. The
holder's ``arm_resume`` releases a pending stop as it releases a latched one.

The robot's own stops (its deadman, a lease hand-over, shutdown) are not
anyone pressing STOP and latch nothing. The latch is the node's memory: a
restarted robot node starts unlatched (the restart itself stopped the arm).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from common.wire.messages import STOP_ROLES

log = logging.getLogger(__name__)

#: commands that can set the arm moving: refused while the stop is latched
MOVES_ARM = frozenset({"arm_jog", "arm_assist"})

#: Refusal reasons, each the name of the counter it increments.
STOP_LATCHED = "commands_stop_latched"
STOP_PENDING = "commands_stop_pending"
NOT_CONTROLLER = "commands_not_controller"
STOP_REFUSED_ROLE = "arm_stops_refused_role"
RESUME_REFUSED = "arm_resumes_refused_not_holder"

#: what a recording (``robot/command`` outcome) says of each refusal
REFUSALS = {
    STOP_LATCHED: "the arm's stop is latched (an arm_resume from the lease holder releases it)",
    STOP_PENDING: "an arm_stop waits for its sender's proof (at most 2 s): the arm holds still",
    NOT_CONTROLLER: "not the lease holder",
    STOP_REFUSED_ROLE: f"only a {' or '.join(sorted(STOP_ROLES))} key may stop the arm",
    RESUME_REFUSED: "only the lease holder may resume the arm",
}


@dataclass
class StopLatch:
    """Whether an operator's stop holds the arm, and who set it."""

    latched: bool = False
    by: str | None = None  # who pressed the stop in force (a roster name, or "operator")
    since_ns: int = 0
    pending: int = 0  # stops awaiting their sender's proof: the arm holds still meanwhile

    def judge(self, action: str, holder: bool, role: str | None = None) -> str | None:
        """Refusal counter for an admitted command, or None to act on it.

        ``holder``: sent by the lease holder (always, without a roster);
        ``role``: the sender's roster role (None without a roster).
        """
        if action == "arm_stop":
            return None if holder or role in STOP_ROLES else STOP_REFUSED_ROLE
        if action == "arm_resume":
            return None if holder else RESUME_REFUSED
        if not holder:
            return NOT_CONTROLLER
        if self.latched and action in MOVES_ARM:
            return STOP_LATCHED
        if self.pending and action in MOVES_ARM:
            return STOP_PENDING
        return None

    def apply(self, action: str, who: str, now_ns: int) -> bool:
        """Act on an ``arm_stop`` or ``arm_resume`` that ``judge`` let through; True on a change."""
        if action == "arm_stop":
            if self.latched:
                return False
            self.latched, self.by, self.since_ns = True, who, now_ns
            log.warning("arm stop latched by %s: no jog moves the arm until a resume", who)
            return True
        if action == "arm_resume":
            if not self.latched:
                return False
            log.warning(
                "arm stop (by %s, %.1f s ago) released by %s",
                self.by,
                (now_ns - self.since_ns) / 1e9,
                who,
            )
            self.latched, self.by = False, None
            return True
        return False
