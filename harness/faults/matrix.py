"""One cell of the fault matrix: a deployment, an operator jogging and grasping, one fault.

Each cell starts a fresh ``Deployment``, waits until the arm follows the
jog, the gripper holds the pipette and the palm feels it, injects one fault
and keeps jogging (the direction flips every 2 s, so the arm stays in its
box) until everything works again or the cell's time is up. Then the
operator lets go, and the arm must be still within the stop budget: no
cell may leave it moving. Every figure is read from outside the process
that failed (``probes``), on the monotonic clock all processes share.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import logging
import math
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

from harness.faults.deployment import ARM_PROCESS, Deployment, DeploymentError
from harness.faults.probes import ArmProbe, GripperProbe, PalmProbe, Sample
from operator_side.node.config import OperatorLinkConfig

log = logging.getLogger(__name__)

KILL, STOP, RESTART, OUTAGE, UNPLUG = "kill -9", "SIGSTOP 2 s", "restart", "outage 5 s", "unplug"
PROCESSES = (
    "robot",
    ARM_PROCESS,
    "operator",
    "router",
    "netsim",
    "video",
    "recorder",
    "ur",
    "gripper",
    "tactile",
    "servos",
)
STOP_S = 2.0
UNPLUG_S = 3.0

#: the issue's budget: the arm still this long after the path of its commands breaks
ARM_STILL_BUDGET_S = 0.4
STILL_M_S = 0.002  # below this the arm counts as still
STILL_FOR_S = 0.15  # ... for this long (a jog reversing passes zero for a few ms)
MOVING_M_S = 0.01
#: no reading of the arm for this long in a UR controller cell: the controller is away
#: (killed, frozen, restarting); far longer than the probe's own stalls on a loaded machine
ARM_UNREADABLE_S = 0.8
JOG_M_S = 0.02
FLIP_S = 2.0
#: the operator's stale_after_ms (150), the renderer's travel to the retract pose at
#: 4 deg a cycle (about 100 ms from the held grasp) and 100 ms for the front panel and
#: the last stimulus's flight
PALM_LIFT_BUDGET_S = 0.35
#: the linkages' travel from pressing the palm to off it (a lift at 0.15 s is off by 0.22 s)
LIFT_TRAVEL_S = 0.1
#: the operator's staleness limit (``stale_after_ms``'s default): a shorter gap lifts nothing
STALE_AFTER_S = OperatorLinkConfig().stale_after_ms / 1000
PALM_PRESSED = 50.0  # counts from the retract pose: a linkage on the palm
GRASP_LEVEL = 20
CLOSE_AGAIN_S = 3.0  # the operator presses close again if the fingers do not hold by then
GRIP_SLACK = 5  # finger counts (of 255) the grip may relax and still hold
READY_TIMEOUT_S = 90.0
RECOVER_TIMEOUT_S = 30.0
#: how long the arm may take to show still after the operator let go at the end before the
#: cell calls it moving on; the node's deadman takes about 0.25 s, a loaded machine's probe
#: may read nothing for a second
RELEASE_WAIT_S = 3.0
UNAFFECTED_S = 3.0  # nothing broke this long after the fault ended: the cell is over


@dataclass(frozen=True)
class Cell:
    target: str  # a process, or "link"
    fault: str

    @property
    def label(self) -> str:
        return f"{self.target}: {self.fault}"


def full_matrix() -> list[Cell]:
    # the arm process has no unit to restart it: the robot node's recovery starts another
    cells = [
        Cell(p, f)
        for p in PROCESSES
        for f in (KILL, STOP, RESTART)
        if not (p == ARM_PROCESS and f == RESTART)
    ]
    cells.append(Cell("link", OUTAGE))
    cells += [Cell(d, UNPLUG) for d in ("tactile", "gripper", "servos")]
    return cells


def quick_matrix() -> list[Cell]:
    """The cells the tests hold too: the robot node killed and frozen, its arm process killed
    (the controller's watchdog stops the arm, the node starts another), the fabric's router
    killed (the nodes reconnect by themselves), netsim's clean restart (it once ignored its stop
    signal and forwarded on), the link."""
    return [
        Cell("robot", KILL),
        Cell("robot", STOP),
        Cell(ARM_PROCESS, KILL),
        Cell("router", KILL),
        Cell("netsim", RESTART),
        Cell("link", OUTAGE),
    ]


MATRICES = {"full": full_matrix, "quick": quick_matrix, "smallest": lambda: [Cell("robot", KILL)]}


@dataclass
class CellResult:
    """One row of the table; times in seconds from the fault, None: did not happen."""

    target: str
    fault: str
    restarted_by: str
    arm_speed_at_fault_m_s: float | None  # the arm must be cruising when the fault comes
    arm_still_s: float | None  # the arm still after the fault (None: it kept following the jog)
    #: the first still reading after the fault, before the link was back (None: never at rest)
    arm_rest_s: float | None
    #: its controller stopped answering (None: it always answered); the arm was not following
    arm_unreadable_s: float | None
    arm_back_s: float | None  # a jog moves it again
    palm_off_s: float | None  # every linkage off the palm
    palm_back_s: float | None  # stimuli press the palm again
    recovered_s: float | None  # both back (or never interrupted: 0)
    gripper_held: bool | None  # None: the gripper's own process died (nothing to read)
    gripper_min_pos: float | None
    released_still_s: float | None  # after the operator let go at the end
    #: the longest stretch without a reading of the arm in the wait after the release
    released_silence_s: float | None
    recording_ok: bool | None
    recording_gap_s: float | None  # last record before the fault, seconds before it
    recording_records: int
    notes: str
    stop_s: float | None = None  # a clean restart: stop signal to the end of the process
    error: str | None = None
    #: netsim's own cells: its new process forwarding again, from the fault (None: not seen)
    link_back_s: float | None = None
    #: the operator's loop woke this much later than due after the fault (None: never 100 ms)
    operator_late_ms: float | None = None
    #: ... and it slept through the link's gap: woke when the link was back, too late to lift
    operator_starved_through_gap: bool = False
    #: the processes' last log lines as the cell ended, for a failed verdict's message (the
    #: deployment's folder is gone by then); not part of the bench's row
    log_tails: str = field(default="", repr=False)
    #: the palm as its probe saw it around the fault, for a failed verdict's message
    palm_trace: str = field(default="", repr=False)

    @property
    def whole_again_s(self) -> float | None:
        return whole_again_s(self.recovered_s, self.link_back_s)

    def as_dict(self) -> dict[str, Any]:
        row = asdict(self)
        del row["log_tails"], row["palm_trace"]
        return row


class Jogger:
    """An operator holding a jog: ``arm_jog`` every 50 ms, flipping direction every 2 s."""

    def __init__(self, deployment: Deployment) -> None:
        self.d = deployment
        self.active = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="jogger", daemon=True)

    def start(self) -> Jogger:
        self.active.set()
        self._thread.start()
        return self

    def _run(self) -> None:
        t0 = time.monotonic()
        while not self._stop.wait(0.05):
            if self.active.is_set():
                sign = 1.0 if int((time.monotonic() - t0) / FLIP_S) % 2 == 0 else -1.0
                self.d.operator_send(
                    {
                        "action": "arm_jog",
                        "velocity": [sign * JOG_M_S, 0, 0, 0, 0, 0],
                        # a jog the operator node reads late (a starved PC) is not sent on
                        "issued_monotonic_s": time.monotonic(),
                    }
                )

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)


def _first(samples: list[Sample], after: float, pred: Callable[[float], bool]) -> float | None:
    for s in samples:
        if s.t_s >= after and pred(s.value):
            return s.t_s
    return None


def back_before_a_stop_was_due(
    arm_still_s: float | None,
    recovered_s: float | None,
    arm_rest_s: float | None = None,
    slack_s: float = 0.0,
) -> bool:
    """The link was whole again before a stop could be seen as a still stretch.

    A restart faster than the stop budget: the arm slowed, never rested, and
    follows the operator's held jog again, as it should. A restart a little
    slower, but within the budget plus the STILL_FOR_S a stop takes to show
    as one: the jog resumed before the still stretch was complete, so the
    arm must have reached rest (``arm_rest_s``, one still reading) within
    the budget; without that reading it is a failure to stop. A stop is not
    the verdict of such a cell.
    """
    if arm_still_s is not None or recovered_s is None:
        return False
    budget = ARM_STILL_BUDGET_S + slack_s
    if recovered_s <= budget:
        return True
    return recovered_s <= budget + STILL_FOR_S and arm_rest_s is not None and arm_rest_s <= budget


def whole_again_s(recovered_s: float | None, link_back_s: float | None) -> float | None:
    """When the path of commands was whole again: what broke came back, and for netsim's
    own cells its new process forwarding (nothing breaking is not a link back at once)."""
    if recovered_s is None or link_back_s is None:
        return recovered_s
    return max(recovered_s, link_back_s)


def back_before_a_lift_could_show(link_back_s: float | None) -> bool:
    """netsim forwarded again before the palm could be seen off it.

    A restarted link simulator that forwards again 0.18 s after the fault
    leaves the operator's newest stimulus stale for 30 ms (its limit is
    0.15 s): the linkages start to lift and are pressed again before their
    travel is over. Not seeing them off is then no verdict on the palm.
    """
    return link_back_s is not None and link_back_s < STALE_AFTER_S + LIFT_TRAVEL_S


def first_rest(samples: list[Sample], after: float, until: float) -> float | None:
    """The first reading below STILL_M_S in ``[after, until]``: the arm reached rest, however
    briefly (the jog's own reversals happen only while its commands arrive)."""
    return next((s.t_s for s in samples if after <= s.t_s <= until and s.value < STILL_M_S), None)


def first_still(samples: list[Sample], after: float) -> float | None:
    """Start of the first stretch of STILL_FOR_S with every sample below STILL_M_S."""
    start: float | None = None
    for s in samples:
        if s.t_s < after:
            continue
        if s.value < STILL_M_S:
            start = s.t_s if start is None else start
            if s.t_s - start >= STILL_FOR_S:
                return start
        else:
            start = None
    return None


def longest_silence(samples: list[Sample], after: float) -> float | None:
    """The longest stretch without a reading from ``after`` to the last one (None: none)."""
    times = [after] + [s.t_s for s in samples if s.t_s >= after]
    if len(times) < 2:
        return None
    return round(max(b - a for a, b in itertools.pairwise(times)), 3)


def first_unreadable(samples: list[Sample], after: float, until: float) -> float | None:
    """The last reading before the first silence of ARM_UNREADABLE_S after ``after``."""
    last = after
    for s in samples:
        if s.t_s < after:
            continue
        if s.t_s - last >= ARM_UNREADABLE_S:
            return last
        last = s.t_s
    return last if until - last >= ARM_UNREADABLE_S else None


@dataclass
class _Timeline:
    t_fault: float
    t_end: float  # when the fault is over (SIGCONT, replug, outage end, restart issued)
    t_release: float = math.inf  # the operator let go: what follows is not the fault's doing


def run_cell(cell: Cell, retract_goals: list[int]) -> CellResult:
    """One cell: its deployment, its fault, what the probes saw."""
    return CellRun(cell, retract_goals).run()


class CellRun:
    """The probes and the deployment of one cell, and the reading of what they saw."""

    def __init__(self, cell: Cell, retract_goals: list[int]) -> None:
        self.cell = cell
        self.d = Deployment()
        self.retract = retract_goals
        self.arm: ArmProbe | None = None
        self.gripper: GripperProbe | None = None
        self.palm: PalmProbe | None = None
        self._link_back: float | None = None  # netsim's cells: when it forwarded again
        self._late_wakes: list[tuple[float, float]] = []  # the operator's, after the fault
        self._close_pressed = -math.inf

    # ------------------------------------------------------------ phases
    def _wait(
        self,
        cond: Callable[[], bool],
        timeout_s: float,
        what: str,
        seen: Callable[[], str] = str,
    ) -> None:
        """Until ``cond``; failing, says ``what`` did not happen, what ``seen`` reads, the logs."""
        deadline = time.monotonic() + timeout_s
        while not cond():
            if time.monotonic() > deadline:
                raise DeploymentError(
                    f"{what} within {timeout_s:.0f} s{seen()}\n{self.d.log_tails(4000)}"
                )
            time.sleep(0.05)

    def _ready(self, jogger: Jogger) -> None:
        t0 = time.monotonic()
        self._wait(
            lambda: _first(self.arm.samples, t0, lambda v: v > MOVING_M_S) is not None,
            READY_TIMEOUT_S,
            "the arm never followed the jog",
        )
        self._wait(
            self._closing_on_the_pipette,
            20.0,
            "the gripper never closed on the pipette",
            lambda: f" (the fingers' last readings, s and counts: {self._last_grips()})",
        )
        self._wait(
            lambda: bool(self.palm.samples) and self.palm.samples[-1].value > PALM_PRESSED,
            20.0,
            "the palm never felt the grasp",
        )
        time.sleep(1.0)  # a steady second before the fault

    def _closing_on_the_pipette(self) -> bool:
        """The operator presses close, and again every CLOSE_AGAIN_S until the fingers hold the
        pipette: a close the robot refused (its lease moved while a starved machine kept the
        operator silent) or the node gave up resending is pressed again, as a person would."""
        if bool(self.gripper.objects) and self.gripper.objects[-1].value == 2:
            return True
        now = time.monotonic()
        if now - self._close_pressed >= CLOSE_AGAIN_S:
            self._close_pressed = now
            self.d.operator_send({"action": "gripper_close", "grip_level": GRASP_LEVEL})
        return False

    def _last_grips(self) -> list[tuple[float, float, float]]:
        """(when, position, object flag) of the gripper probe's last five readings."""
        t0 = self.arm.samples[0].t_s if self.arm.samples else 0.0
        pairs = zip(self.gripper.samples[-5:], self.gripper.objects[-5:], strict=False)
        return [(round(p.t_s - t0, 2), p.value, o.value) for p, o in pairs]

    def _inject(self) -> _Timeline:
        d, target, fault = self.d, self.cell.target, self.cell.fault
        self._wait(self._cruising, 10.0, "the arm never cruised at the jog's speed (load?)")
        if fault == OUTAGE:
            t_cut, t_back = d.cut_link()
            time.sleep(max(0.0, t_back - time.monotonic()))
            return _Timeline(t_cut, t_back)
        t_fault = time.monotonic()
        if fault == KILL:
            d.signal(target, signal.SIGKILL)  # the supervisor starts it again, as its rule says
            return _Timeline(t_fault, t_fault)
        if fault == STOP:
            d.signal(target, signal.SIGSTOP)
            time.sleep(STOP_S)
            d.signal(target, signal.SIGCONT)
            return _Timeline(t_fault, time.monotonic())
        if fault == RESTART:
            return _Timeline(t_fault, d.clean_restart(target))
        if fault == UNPLUG:
            d.signal(target, signal.SIGUSR1)
            time.sleep(UNPLUG_S)
            d.signal(target, signal.SIGUSR2)
            return _Timeline(t_fault, time.monotonic())
        raise ValueError(f"unknown fault {fault!r}")

    def _cruising(self) -> bool:
        """The arm at the jog's speed now, not stalled by a loaded machine nor reversing."""
        recent = self.arm.between(time.monotonic() - 0.1)
        return bool(recent) and min(s.value for s in recent) > 0.75 * JOG_M_S

    def _broken_and_back(self, tl: _Timeline) -> tuple[float | None, ...]:
        arm = self.arm.between(tl.t_fault, tl.t_release)
        palm = self.palm.between(tl.t_fault, tl.t_release)
        arm_still = first_still(arm, tl.t_fault)
        unreadable = self._controller_away(arm, tl, min(tl.t_release, time.monotonic()))
        if unreadable is not None and (arm_still is None or unreadable < arm_still):
            arm_still = unreadable  # a controller that is away is not following the jog
        arm_back = (  # after the reading that broke (the last one before a silence moved)
            _first(arm, max(arm_still + 1e-6, tl.t_end), lambda v: v > MOVING_M_S)
            if arm_still is not None
            else None
        )
        palm_off = _first(palm, tl.t_fault, lambda v: v == 0)
        palm_back = (
            _first(palm, max(palm_off, tl.t_end), lambda v: v > PALM_PRESSED)
            if palm_off is not None
            else None
        )
        return arm_still, arm_back, palm_off, palm_back

    def _controller_away(self, arm: list[Sample], tl: _Timeline, until: float) -> float | None:
        """When the UR controller stopped answering, in its own cells only: elsewhere a
        silence is the probe's stall, and must never pass for an arm that stopped in time."""
        if self.cell.target != "ur":
            return None
        return first_unreadable(arm, tl.t_fault, until)

    def _settled(self, tl: _Timeline) -> bool:
        arm_still, arm_back, palm_off, palm_back = self._broken_and_back(tl)
        now = time.monotonic()
        arm_done = arm_back is not None or (arm_still is None and now > tl.t_end + UNAFFECTED_S)
        palm_done = palm_back is not None or (palm_off is None and now > tl.t_end + UNAFFECTED_S)
        return arm_done and palm_done

    # ------------------------------------------------------------ the cell
    def run(self) -> CellResult:
        d = self.d
        with d:
            self.arm = ArmProbe(d.ur_host).start()
            self.gripper = GripperProbe(*d.gripper).start()
            self.palm = PalmProbe(d.servo_status, self.retract).start()
            jogger = Jogger(d).start()
            try:
                self._ready(jogger)
                tl = self._inject()
                deadline = tl.t_end + RECOVER_TIMEOUT_S
                while not self._settled(tl) and time.monotonic() < deadline:
                    time.sleep(0.1)
                tails = d.log_tails(4000)
                jogger.active.clear()
                self._link_back = self._netsim_back(tl)
                self._late_wakes = [w for w in self.d.operator_late_wakes() if w[1] >= tl.t_fault]
                tl.t_release = t_release = time.monotonic()
                released_still = self._still_after(t_release)
            finally:
                jogger.close()
                for probe in (self.arm, self.gripper, self.palm):
                    probe.close()
        result = self._result(tl, released_still, t_release)
        notes = [self._controller_account(tl.t_fault)]
        if result.arm_still_s is not None:  # a probe that read nothing for a while sees late
            until = tl.t_fault + result.arm_still_s
            gap = longest_silence([s for s in self.arm.samples if s.t_s <= until], tl.t_fault)
            notes.append(f"the arm's probe read nothing for at most {gap} s before it saw it still")
        return dataclasses.replace(
            result, notes="; ".join(notes), log_tails=tails, palm_trace=self._palm_trace(tl)
        )

    def _palm_trace(self, tl: _Timeline) -> str:
        """The palm's probe around the fault (s after it): each change of its distance from the
        retract pose, and the bus's goal writes, so a late lift says whether the bus took
        the write late or the probe read it late."""
        t0, t1 = tl.t_fault - 0.5, min(tl.t_release, tl.t_fault + 5.0)
        changes, last = [], None
        for s in self.palm.between(t0, t1):
            if s.value != last:
                changes.append(f"{s.t_s - tl.t_fault:+.3f}: {s.value:g}")
                last = s.value
        writes = sorted(
            {round(t - tl.t_fault, 3) for t, _, _ in self.palm.goal_writes if t0 <= t < t1}
        )
        return (
            f"palm distance from the retract pose (counts), each change: {changes[:40]}; "
            f"the bus's goal writes (s after the fault): {writes[:40]}"
        )

    def _controller_account(self, t_fault: float) -> str:
        """What the UR simulator says ended its program after the fault, and when (ms after
        it, on the machine's clock): from its final stats, printed to its log as it stopped."""
        unit = self.d.units.get("ur")
        text = unit.handle.log_text() if unit is not None and unit.handle is not None else ""
        finals = [ln for ln in text.splitlines() if ln.startswith('{"final"')]
        if not finals:
            return "the UR simulator printed no final stats"
        ends = json.loads(finals[-1])["final"].get("program_ends", [])
        after = [f"{(t - t_fault) * 1e3:+.0f} ms: {why}" for t, why in ends if t >= t_fault]
        return "the controller ended its program " + ("; ".join(after) if after else "never")

    def _still_after(self, t_release: float) -> float | None:
        """When the arm came to rest after the operator let go (None: not in RELEASE_WAIT_S)."""
        deadline = t_release + RELEASE_WAIT_S
        while (still := first_still(self.arm.samples, t_release)) is None:
            if time.monotonic() > deadline:
                return None
            time.sleep(0.05)
        return still

    def _netsim_back(self, tl: _Timeline) -> float | None:
        """When a restarted or killed netsim forwarded again: how long the link was away."""
        if self.cell.target != "netsim" or self.cell.fault not in (KILL, RESTART):
            return None
        back = [t for t in self.d.netsim_started() if t >= tl.t_fault]
        return round(back[0] - tl.t_fault, 3) if back else None

    def _result(self, tl: _Timeline, released_still: float | None, t_release: float) -> CellResult:
        arm_still, arm_back, palm_off, palm_back = self._broken_and_back(tl)
        since = lambda t: None if t is None else round(t - tl.t_fault, 3)  # noqa: E731
        backs = [b for b, broke in ((arm_back, arm_still), (palm_back, palm_off)) if broke]
        recovered = None if any(b is None for b in backs) else max(backs, default=tl.t_fault)
        at_fault = self.arm.between(tl.t_fault - 0.05, tl.t_fault)
        held, min_pos = self._gripper_held(tl)
        rec_ok, rec_gap, rec_n = self._recording(tl)
        unit = self.d.units.get(self.cell.target)
        by = restarted_by(self.cell, unit.policy if unit else None)
        if unit is not None and unit.stops:
            took, killed = unit.stops[-1]
            if killed:
                by += f"; ignored its stop signal, killed after {took:.0f} s"
        return CellResult(
            target=self.cell.target,
            fault=self.cell.fault,
            restarted_by=by,
            arm_speed_at_fault_m_s=round(at_fault[-1].value, 4) if at_fault else None,
            arm_still_s=since(arm_still),
            arm_rest_s=since(
                first_rest(
                    self.arm.samples,
                    tl.t_fault,
                    recovered if recovered is not None else tl.t_release,
                )
            ),
            arm_unreadable_s=since(
                self._controller_away(self.arm.between(tl.t_fault), tl, tl.t_release)
            ),
            arm_back_s=since(arm_back),
            palm_off_s=since(palm_off),
            palm_back_s=since(palm_back),
            recovered_s=since(recovered),
            gripper_held=held,
            gripper_min_pos=min_pos,
            released_still_s=None
            if released_still is None
            else round(released_still - t_release, 3),
            released_silence_s=longest_silence(self.arm.between(t_release), t_release),
            recording_ok=rec_ok,
            recording_gap_s=rec_gap,
            recording_records=rec_n,
            notes="",
            stop_s=round(unit.stops[-1][0], 3) if unit is not None and unit.stops else None,
            link_back_s=self._link_back,
            operator_late_ms=max(
                (round((woke - due) * 1e3) for due, woke in self._late_wakes), default=None
            ),
            operator_starved_through_gap=self._starved_through_gap(tl),
        )

    def _starved_through_gap(self, tl: _Timeline) -> bool:
        """The operator's loop was due while the link was away and woke only about when it
        was back (within a lift's travel): it never saw the link stale, through no fault of
        its own logic (a machine that starved it)."""
        if self._link_back is None:
            return False
        back = tl.t_fault + self._link_back
        return any(due < back and woke > back - LIFT_TRAVEL_S for due, woke in self._late_wakes)

    def _gripper_held(self, tl: _Timeline) -> tuple[bool | None, float | None]:
        """Held: the fingers never opened from the pipette (a hold re-targets where they are,
        so the object flag may turn from 'stopped on an object' to 'at position': still held)."""
        before = self.gripper.between(tl.t_fault - 1.0, tl.t_fault)
        after = self.gripper.between(tl.t_fault)
        if not before or not after:
            return None, None
        grip = min(s.value for s in before)
        lowest = min(s.value for s in after)
        if self.cell.target == "gripper" and self.cell.fault in (KILL, RESTART):
            return None, lowest  # a new simulator process: the grip died with the old one
        return lowest >= grip - GRIP_SLACK, lowest

    def _recording(self, tl: _Timeline) -> tuple[bool | None, float | None, int]:
        """Whether the recorder's file reads back up to the fault: its last record before it."""
        from common.wire.codec import DecodeError
        from operator_side.record_cli import read_records

        path = self.d.recording
        if not path.exists():
            return False, None, 0
        times: list[int] = []
        try:
            for t_ns, _name, _msg in read_records(path):
                times.append(t_ns)
        except DecodeError:
            return False, None, len(times)
        before = [t for t in times if t < tl.t_fault * 1e9]
        if not before:
            return False, None, len(times)
        gap = round(tl.t_fault - max(before) / 1e9, 3)
        return gap < 1.0, gap, len(times)


def restarted_by(cell: Cell, policy: Any) -> str:
    if cell.fault in (STOP, OUTAGE, UNPLUG):
        return "-"
    if cell.target == ARM_PROCESS:
        return "the robot node's recovery"
    systemd = policy is not None and policy.unit
    if cell.fault == RESTART:
        return "systemctl restart" if systemd else "a human (restart)"
    if systemd:
        return f"systemd ({policy.restart_sec:g} s)"
    if policy is not None:
        return f"power/link back ({policy.restart_sec:g} s)"
    return "nobody (no unit)"


def run_cells(
    cells: list[Cell], progress: Callable[[str], None] | None = None
) -> list[dict[str, Any]]:
    from operator_side.palm.renderer import LinkGlideRenderer, RendererConfig
    from operator_side.servos.feetech import FeetechConfig

    retract = LinkGlideRenderer(RendererConfig(), FeetechConfig().calibration).retract_goals
    rows = []
    for cell in cells:
        t0 = time.monotonic()
        try:
            row = run_cell(cell, retract).as_dict()
        except DeploymentError as e:
            row = {"target": cell.target, "fault": cell.fault, "error": str(e)[:4000]}
        row["seconds"] = round(time.monotonic() - t0, 1)
        rows.append(row)
        if progress is not None:
            progress(f"  faults: {cell.label}: {row}")
    return rows
