"""The arm process: the UR driver alone in a process, its keep-alive real-time.

Started by the robot node (``ArmProcess``) as ``python -m robot_side.arm.process``.
It builds the arm's driver (the kind the node's config names), raises the
driver's deadman and keep-alive threads to SCHED_FIFO where granted, and
then does three things:

- answers the node's calls, one JSON line each way on stdin/stdout
  (connect, jog, stop, moves, reads): not time-critical, and never in the
  way of the keep-alive, which runs on its own thread with the interpreter
  lock nearly always free (nothing else in this process computes);
- writes the newest pose, the connection's state, the keep-alive's
  timing and the driver's telemetry into the shared state file at the
  heartbeat's rate (``state.py``), which the node reads without waiting
  (its heartbeats, its telemetry poll, its reconnect decisions);
- when the node goes (its end of stdin closes: killed, crashed or done),
  stops the arm, ends the control script and exits at once.

SIGINT and SIGTERM are the node's to act on: a Ctrl-C or ``systemctl stop``
reaches the whole group, and the node stops the arm through us and then
closes our stdin. If this process dies, the controller's watchdog stops the
arm within its window, as for any other silence.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from common.clocks.clock import now_s
from common.config.typed import from_dict
from common.devices.lifecycle import load_object
from common.logs import BurstLog
from common.logs import configure as configure_logging
from common.process.realtime import PeriodStats, raise_this_thread
from robot_side.arm.base import SAFETY_THREAD_NICE, Arm
from robot_side.arm.process.state import TELEMETRY_STATE_KEYS, WRITE_EVERY_S, StateView
from robot_side.devices.stdio_child import serve_stdio

log = logging.getLogger(__name__)

#: the calls the node makes through the pipe
REMOTE_METHODS = frozenset(
    {
        "connect",
        "disconnect",
        "jog",
        "stop_arm",
        "move_to",
        "move_finished",
        "tcp_pose",
        "joint_positions",
        "status",
    }
)
#: the keep-alive's timing percentiles are computed this often (the rest of a state write is
#: a handful of cache reads)
SUMMARY_EVERY_S = 1.0


@dataclass
class ArmProcessSpec:
    """What the node hands its arm process (as JSON on its command line)."""

    driver: str = ""  # "module:Class" of the arm's driver
    driver_config: str = "{}"  # its Config, as JSON
    state_file: str = ""
    realtime_priority: int = 0


def name_os_threads() -> None:
    """Each Python thread of this process under its own name in ``/proc`` and ``top -H``
    (the bench's CPU per thread, a user's ``top``): Python leaves them all "python"."""
    for t in threading.enumerate():
        if t is threading.main_thread() or t.native_id is None:
            continue
        name = "urarm-ctrl" if t.name.startswith("urarm-ctrl") else t.name[:15]
        with contextlib.suppress(OSError), open(f"/proc/self/task/{t.native_id}/comm", "w") as f:
            f.write(name)  # OSError: it ended meanwhile


class ServedArm:
    """The driver's calls as the pipe carries them (plain values in, plain values out)."""

    def __init__(self, arm: Arm, written: Callable[[], None] = lambda: None) -> None:
        self.arm = arm
        self.written = written  # the shared state written now

    def connect(self) -> None:
        self.arm.connect()
        name_os_threads()
        self.written()  # the node reads a connected arm from the moment the reply reaches it

    def disconnect(self) -> None:
        self.arm.disconnect()

    def jog(self, velocity: list[float], issued_at_s: float | None) -> Any:
        return self.arm.jog(velocity, issued_at_s)

    def stop_arm(self) -> None:  # "stop" is the pipe's own: end the process
        self.arm.stop()

    def move_to(self, pose: list[float], speed: float | None) -> None:
        self.arm.move_to(pose, speed, wait=False)

    def move_finished(self) -> bool:
        return self.arm.move_finished()

    def tcp_pose(self) -> Any:
        return self.arm.tcp_pose()

    def joint_positions(self) -> Any:
        return self.arm.joint_positions()

    def status(self) -> dict[str, Any]:
        return json.loads(json.dumps(self.arm.status(), default=float))


class StateWriter:
    """Writes the arm's newest state every ``WRITE_EVERY_S``, on a thread of its own."""

    def __init__(self, arm: Arm, view: StateView) -> None:
        self.arm = arm
        self.view = view
        self._quit = threading.Event()
        self._summary: dict[str, float] = {}
        self._summary_due = 0.0
        self._writing = threading.Lock()  # one writer at a time (the seqlock has one side)
        self._telemetry_failed = BurstLog(log, "arm process", level=logging.DEBUG)
        self._thread = threading.Thread(target=self._run, name="arm-state", daemon=True)

    def start(self) -> StateWriter:
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._quit.wait(WRITE_EVERY_S):
            self.write_now()

    def write_now(self) -> None:
        """The newest state to the shared file (this thread's turn, or a connect's reply)."""
        with self._writing:
            try:
                self.view.write(self._state())
            except Exception:  # an interface closing under us: the next turn writes again
                log.debug("arm state not written", exc_info=True)

    def _state(self) -> dict[str, float]:
        arm, now = self.arm, now_s()
        connected = arm.is_connected
        out: dict[str, float] = {
            "t_write_s": now,
            "connected": float(connected),
            "needs_reconnect": float(bool(getattr(arm, "needs_reconnect", False))),
        }
        live = arm.live_readings() if connected else {}
        if live:
            out["live"] = 1.0
            out.update(live)
        if now >= self._summary_due:
            self._summary = arm.keep_alive_periods.summary()
            self._summary_due = now + SUMMARY_EVERY_S
        if connected:
            out.update(self._take_telemetry())
        out.update({f"keepalive_{key}": value for key, value in self._summary.items()})
        got = arm.keep_alive_scheduling
        if got is not None:
            out["keepalive_realtime"] = float(got.realtime)
            out["keepalive_level"] = float(got.level)
        return out

    def _take_telemetry(self) -> dict[str, float]:
        """What only the driver knows of the telemetry, for the node's poll (which reads it
        here instead of asking through the pipe: no round trip, nothing waiting behind a
        stop); the pose and speed are the live readings, the rest is the node's own."""
        try:
            got = self.arm.driver_state()
        except Exception as e:  # stale, lost or stopped: the node's poll says so
            self._telemetry_failed(f"arm telemetry not read: {e}")
            return {"telemetry_ok": 0.0}
        return {"telemetry_ok": 1.0, **{k: got.get(k, 0.0) for k in TELEMETRY_STATE_KEYS}}

    def stop(self) -> None:
        self._quit.set()
        self._thread.join(1.0)


def _warm_up() -> None:
    """Run once what the state writer runs, before the keep-alive exists: numpy's percentile
    imports modules on its first call, holding the interpreter lock for tens of ms."""
    stats = PeriodStats(1.0)
    for t in (0.0, 1.0, 2.0):
        stats.woke(t)
    stats.summary()


def main(argv: list[str] | None = None) -> None:
    import argparse

    ap = argparse.ArgumentParser(prog="python -m robot_side.arm.process", description=__doc__)
    ap.add_argument("--stdio", action="store_true", help="take requests as JSON lines on stdin")
    ap.add_argument("--config-json", required=True, help="an ArmProcessSpec as JSON")
    ap.add_argument("--log-level", type=int, default=logging.INFO)
    args = ap.parse_args(argv)
    # the pipe to the node is ours alone: ur-rtde prints to standard output (its reconnect
    # messages), which would corrupt a reply, so fd 1 becomes the log's (stderr)
    replies = os.fdopen(os.dup(sys.stdout.fileno()), "w")
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())
    configure_logging(args.log_level, "%(asctime)s %(levelname)s arm-process %(name)s: %(message)s")
    for sig in (signal.SIGINT, signal.SIGTERM):  # the node stops the arm, then closes stdin
        signal.signal(sig, signal.SIG_IGN)
    spec = from_dict(ArmProcessSpec, json.loads(args.config_json), where="arm process")
    try:
        cls = load_object(spec.driver)
        arm: Arm = cls(from_dict(cls.Config, json.loads(spec.driver_config), where="arm"))
    except Exception as e:  # the node checked this config already; say why anyway
        replies.write(json.dumps({"error": f"{type(e).__name__}: {e}"}) + "\n")
        replies.flush()
        raise SystemExit(f"arm process: {e}") from None
    arm.realtime_priority = spec.realtime_priority
    if spec.realtime_priority > 0:
        # Every thread of this process real-time, one step under the keep-alive: a thread
        # holding the interpreter lock must never be preempted by the machine's other work,
        # or the keep-alive waits for the lock as long (measured: 62 ms, with one ordinary
        # thread beside it). New threads inherit this (ur-rtde's, the state writer, the
        # driver's worker); each sleeps between short turns. Threads made before this stay
        # fair. A BLAS pool's spin while they wait for work: raised with this process, one
        # spun 90-120 ms on a core nothing else could take at every start (a reconnect's too),
        # and the robot node's frame loop waited for a CPU. The node starts this process with
        # none (ONE_THREAD_POOLS): its arithmetic is a few six-vectors.
        got = raise_this_thread(max(1, spec.realtime_priority - 1), SAFETY_THREAD_NICE)
        log.info("arm process %d at %s", os.getpid(), got.describe())
    _warm_up()
    view = StateView(spec.state_file)
    writer = StateWriter(arm, view).start()

    def on_exit() -> None:
        writer.stop()
        t0 = time.monotonic()
        try:
            arm.disconnect()  # stops the arm and ends the control script
        except Exception:
            log.exception("arm process: disconnect at exit failed")
        log.info("arm process %d: arm stopped and disconnected in %.0f ms", os.getpid(),
                 (time.monotonic() - t0) * 1000)  # fmt: skip
        view.close()

    served = ServedArm(arm, writer.write_now)
    serve_stdio(served, REMOTE_METHODS, os.getpid(), sys.stdin, replies, on_exit)
