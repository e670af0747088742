"""A test's own router client, and an operator process jogging, for the fleet tests."""

from __future__ import annotations

import itertools
import signal
import threading
import time
from collections.abc import Callable

import numpy as np

from common.wire.messages import Heartbeat, Stimulus
from harness.fleet import Fleet


class Monitor:
    """The test's own router client (the recorder's key): robot heartbeats and stimuli,
    timed, read with the product's own ``FabricSubscriber``."""

    def __init__(self, fleet: Fleet, key: str, robots: list[str]) -> None:
        self.heartbeats: list[tuple[int, Heartbeat]] = []
        self.stimulus_times: list[int] = []  # arrival here, our clock
        self.session = None
        self.sub = self._fabric(fleet, key, robots)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _fabric(self, fleet: Fleet, key: str, robots: list[str]):
        from common.fabric import keyexprs
        from common.fabric.link import FabricSubscriber
        from common.fabric.session import FabricConfig, cert_files, client_config, open_session

        fabric = FabricConfig(router_endpoint=fleet.router_endpoint)
        files = cert_files(fleet.cert_dir, key, "monitor")
        self.session = open_session(client_config(fabric, files, "monitor"), "monitor")
        keys = tuple(keyexprs.robot_key(r, k) for r in robots for k in ("heartbeat", "stimulus"))
        # every heartbeat and stimulus, not the newest of each: a queue per key of its own
        return FabricSubscriber(self.session, keys, expect_name=None, latest_value=False)

    def _run(self) -> None:
        while not self._stop.is_set():
            if self.sub.poll(0.05):
                for msg, t in self.sub.drain():
                    if isinstance(msg, Heartbeat):
                        self.heartbeats.append((t, msg))
                    elif isinstance(msg, Stimulus):
                        self.stimulus_times.append(t)

    def holder_since(self, key: bytes, t0: int) -> int | None:
        """When the robot first named ``key`` its holder after ``t0``: its heartbeat's send stamp.

        The robot's stamp (this machine's monotonic clock), not this client's
        arrival time: a test thread starved beside other deployments must not
        read as a slow hand-over (one such read 55 ms against 7).
        """
        for _, hb in list(self.heartbeats):
            if hb.t_send_ns >= t0 and hb.lease_holder == key:
                return hb.t_send_ns
        return None

    def largest_stimulus_gap_ms(self) -> float:
        """The longest the robots' stimulus stream went quiet, as this client saw it.

        A pause over the operator's staleness limit lifts its palm, as it
        should: a test that finds a lift-off can tell a stalled robot or
        machine (this gap too) from a lift-off with the stream flowing.
        """
        times = sorted(self.stimulus_times)
        return max((b - a for a, b in itertools.pairwise(times)), default=0) / 1e6

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        self.sub.close()
        if self.session is not None:
            self.session.close()


def jog_for(proc, velocity: list[float], seconds: float) -> None:
    """Jog at 20/s for ``seconds`` (or until the process ended)."""
    end = time.monotonic() + seconds
    jog_while(proc, velocity, lambda: time.monotonic() >= end)


def jog_while(proc, velocity: list[float], done: Callable[[], bool]) -> None:
    """Jog at 20/s until ``done()`` (or the process ended)."""
    while not done() and proc.popen.poll() is None:
        try:
            proc.send({"action": "arm_jog", "velocity": velocity})
        except BrokenPipeError:  # the process was killed on purpose
            return
        time.sleep(0.05)


def kill_mid_jog_and_time_the_stop(fleet: Fleet, controller, sim, jog: list[float]) -> float:
    """Kill ``controller``'s process while it jogs ``sim``'s arm; ms until the arm was at rest.

    The rest is read from the UR simulator (its own record, monotonic as ``now_ns``: this
    process's poll may have been starved past the moment). Fails if the arm never moved
    under the jog, never stopped within 2 s, or moved again after it stopped.
    """
    from common.clocks.clock import now_ns

    jogging = threading.Thread(target=jog_for, args=(controller, jog, 4.0))
    jogging.start()
    # a loaded machine delays the first jogs (process, hop, robot, all on 2 cores): wait for
    # the motion, with every process's log if it never comes
    fleet.wait_for(
        lambda: np.linalg.norm(sim.tcp_speed()[:3]) > 0.01, 3.0, "the arm to move under the jog"
    )
    time.sleep(0.3)  # mid-jog
    t_kill = now_ns()
    controller.popen.send_signal(signal.SIGKILL)
    jogging.join()
    stopped_at = None
    while (now_ns() - t_kill) < 2e9:
        if np.linalg.norm(sim.tcp_speed()[:3]) < 1e-4:
            stopped_at = now_ns()
            break
        time.sleep(0.005)
    assert stopped_at is not None, "the arm kept moving after its controller died"
    since = sim.at_rest_since(1e-4, 1e-3)
    assert since is not None, "the arm moved again after it stopped"
    return (min(stopped_at, round(since * 1e9)) - t_kill) / 1e6
