"""How faithful the simulator is, measured from outside as a user would.

A PUB sends small messages carrying their send time at a steady rate to
two SUBs on loopback: one connected directly, one through ``deepxpalm
netsim`` running as its own process (the deployed arrangement, with no
interpreter lock shared with the rig). The two paths alternate half a
period apart, so both see the same machine in the same run. What the
scenario configures is then compared with what the SUB behind the simulator saw minus
what the direct one saw. The rig binds its ends on ports of their own; the
simulator binds the operator's side on port 0 and says where in its ``READY=1``
(``deploy.units``).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zmq

from common.errors import LinkError
from common.netsim.impairments import DirectionConfig
from common.netsim.scenario import load_scenario
from deploy.units.readiness import NotReady
from deploy.units.service import Service

log = logging.getLogger(__name__)

#: Percentiles compared, as fractions.
QUANTILES = (0.05, 0.5, 0.95, 0.99)
#: The direct path's p50/p99 may grow by at most this through a zero-delay simulator, ms.
TRANSPARENT_P50_MS = 0.15
TRANSPARENT_P99_MS = 0.5
#: A delayed path's p5/p50/p95 must be within this many ms, or this share, of the target.
DELAYED_ABS_MS = 0.5
DELAYED_REL = 0.05
_WARMUP_S = 1.0


def percentile(sorted_values: list[float], q: float) -> float:
    """Nearest-rank percentile of an already sorted list."""
    if not sorted_values:
        return float("nan")
    i = min(len(sorted_values) - 1, max(0, round(q * (len(sorted_values) - 1))))
    return sorted_values[i]


@dataclass
class FidelityRun:
    """One scenario's run: latencies per path and what the scenario configures."""

    scenario: str
    mode: str
    seconds: float
    rate_hz: float
    direct_ms: list[float] = field(default_factory=list)
    via_ms: list[float] = field(default_factory=list)
    configured: dict[float, float] = field(default_factory=dict)  # q -> ms (to_operator)
    netsim_stats: dict[str, Any] = field(default_factory=dict)

    def quantiles(self, values: list[float]) -> dict[float, float]:
        s = sorted(values)
        return {q: percentile(s, q) for q in QUANTILES}

    def verdicts(self, scaled_to_hop: bool = False) -> dict[str, bool]:
        """Per checked percentile, whether it met the criterion.

        ``scaled_to_hop``: judged on this machine's hop, as the tests do. At zero
        delay the forwarder's whole cost is one more process woken and one more
        loopback hop: mostly the kernel's wake-up, which no forwarder can
        undercut. The bench's absolute goals (0.15 ms at p50, 0.5 ms at p99, met
        where the bench table was taken, its direct hop 0.07 ms) hold wherever a
        direct hop costs less than that; on a machine whose direct hop itself
        costs more (a CI runner's direct p50 was 0.30 ms, p99 2.5 ms), the extra
        hop may cost what a direct one does there, and no more.

        A delayed path's target is the configured delay plus one direct hop, but
        the simulated path takes two hops and a timer's wake-up. The bench's
        tolerance (0.5 ms or 5 %) absorbs the second hop where a hop costs what
        the bench assumes; where the direct hop costs more (a quiet clean-clone
        run measured a direct p50 of 0.93 ms, six times the usual, and the relay
        path 1.5 ms above its target), scaled, the tolerance grows by that
        excess, and no more: a simulator that adds its own milliseconds still fails.
        """
        if not self.via_ms:
            return {"p50": False}
        d, v = self.quantiles(self.direct_ms), self.quantiles(self.via_ms)
        hop = d if scaled_to_hop else dict.fromkeys(d, 0.0)
        if all(ms == 0 for ms in self.configured.values()):
            return {
                "p50": v[0.5] - d[0.5] <= max(TRANSPARENT_P50_MS, hop[0.5]),
                "p99": v[0.99] - d[0.99] <= max(TRANSPARENT_P99_MS, hop[0.99]),
            }
        out = {}
        for q in (0.05, 0.5, 0.95):
            target = self.configured[q] + d[q]
            slack = max(DELAYED_ABS_MS, DELAYED_REL * target)
            slack += max(0.0, hop[q] - TRANSPARENT_P50_MS)
            out[f"p{round(q * 100)}"] = abs(v[q] - target) <= slack
        return out

    def scaled_verdicts(self) -> dict[str, bool]:
        """The verdicts judged on this machine's hop (``verdicts(scaled_to_hop=True)``)."""
        return self.verdicts(scaled_to_hop=True)

    def ok(self) -> bool:
        return bool(self.via_ms) and all(self.verdicts().values())

    def as_dict(self) -> dict[str, Any]:
        d, v = self.quantiles(self.direct_ms), self.quantiles(self.via_ms)
        return {
            "scenario": self.scenario,
            "mode": self.mode,
            "seconds": self.seconds,
            "rate_hz": self.rate_hz,
            "n_direct": len(self.direct_ms),
            "n_via": len(self.via_ms),
            "direct_ms": {f"p{round(q * 100)}": d[q] for q in QUANTILES},
            "via_ms": {f"p{round(q * 100)}": v[q] for q in QUANTILES},
            "configured_ms": {f"p{round(q * 100)}": self.configured[q] for q in QUANTILES},
            "verdicts": self.verdicts(),
            "ok": self.ok(),
            "netsim_own_latency_us": self.netsim_stats.get("own_latency_us"),
            "netsim_connections": self.netsim_stats.get("connections"),
        }


def configured_quantiles(config: DirectionConfig) -> dict[float, float]:
    """The configured one-way delay at each checked percentile, ms."""
    return {q: config.delay_quantile_ms(q) for q in QUANTILES}


def _sub(ctx: zmq.Context, endpoint: str) -> zmq.Socket:
    s = ctx.socket(zmq.SUB)
    s.setsockopt(zmq.LINGER, 0)
    s.setsockopt(zmq.SUBSCRIBE, b"")
    s.connect(endpoint)
    return s


def measure(
    scenario: str,
    *,
    seconds: float = 20.0,
    rate_hz: float = 100.0,
    seed: int = 1,
    mode: str = "stream",
    payload_bytes: int = 64,
    netsim_args: tuple[str, ...] = (),
    netsim_cpus: set[int] | None = None,
) -> FidelityRun:
    """Run the rig once: ``rate_hz`` messages a second on each path for ``seconds``."""
    config = load_scenario(scenario).to_operator
    run = FidelityRun(scenario, mode, seconds, rate_hz, configured=configured_quantiles(config))
    ctx = zmq.Context()
    socks: list[zmq.Socket] = []

    def bound(kind: int) -> tuple[zmq.Socket, str]:  # one end of the rig, on a port of its own
        s = ctx.socket(kind)
        s.setsockopt(zmq.LINGER, 0)
        s.bind("tcp://127.0.0.1:*")
        socks.append(s)
        return s, s.getsockopt(zmq.LAST_ENDPOINT).decode()

    pub_direct, direct_at = bound(zmq.PUB)
    pub_via, via_robot_at = bound(zmq.PUB)  # the robot's telemetry, as netsim sees it
    _, robot_cmd_at = bound(zmq.SUB)  # the robot's command end: nothing is sent to it
    workdir = Path(tempfile.mkdtemp(prefix="deepxpalm-fidelity-"))
    stats_path = workdir / "netsim-stats.json"
    argv = [
        *("netsim", "--scenario", scenario, "--mode", mode, "--seed", str(seed)),
        *("--robot-telemetry", via_robot_at, "--robot-commands", robot_cmd_at),
        *("--operator-telemetry", "tcp://127.0.0.1:0", "--operator-commands", "tcp://127.0.0.1:0"),
        *("--stats-file", str(stats_path), "--set", "netsim.report_interval_s=0", *netsim_args),
    ]
    netsim = Service("netsim", argv, workdir / "netsim.log")
    netsim.start()
    if netsim_cpus:  # a caller pinned to one core: the simulator is a process of its own
        os.sched_setaffinity(netsim.pid, netsim_cpus)
    try:
        try:
            op_tel_at = netsim.wait_ready().endpoints["operator_telemetry"]
        except NotReady as e:
            raise LinkError(f"the simulated path never came up: {e}") from None
        sub_direct = _sub(ctx, direct_at)
        sub_via = _sub(ctx, op_tel_at)
        socks += [sub_direct, sub_via]
        got: dict[str, list[tuple[int, int]]] = {"d": [], "v": []}
        stop = threading.Event()

        def receive() -> None:
            poller = zmq.Poller()
            poller.register(sub_direct, zmq.POLLIN)
            poller.register(sub_via, zmq.POLLIN)
            while not stop.is_set():
                for sock, _ in poller.poll(20):
                    data = sock.recv(zmq.NOBLOCK)
                    t = time.monotonic_ns()
                    key = "d" if sock is sub_direct else "v"
                    got[key].append((int.from_bytes(data[1:9], "little"), t))

        thread = threading.Thread(target=receive, name="fidelity-rx", daemon=True)
        thread.start()
        # Until the simulated path delivers: the subscriptions joined (ZeroMQ's slow joiner)
        deadline = time.monotonic() + 15
        while not got["v"]:
            if time.monotonic() > deadline or not netsim.alive():
                raise LinkError(f"the simulated path never delivered: {netsim.log_tail()}")
            pub_via.send(b"w" + time.monotonic_ns().to_bytes(8, "little"))
            pub_direct.send(b"w" + time.monotonic_ns().to_bytes(8, "little"))
            time.sleep(0.05)
        time.sleep(_WARMUP_S)
        period_ns = round(1e9 / rate_hz)
        pad = bytes(max(0, payload_bytes - 9))
        t_first = time.monotonic_ns() + period_ns
        t_measure = t_first
        n = round(seconds * rate_hz)
        for i in range(n):
            for offset, sock, tag in ((0, pub_direct, b"d"), (period_ns // 2, pub_via, b"v")):
                target = t_first + i * period_ns + offset
                _sleep_until(target)
                sock.send(tag + time.monotonic_ns().to_bytes(8, "little") + pad)
        time.sleep(1.0 + 2 * max(run.configured.values()) / 1e3 + 0.5)
        stop.set()
        thread.join(timeout=2)
        for key, out in (("d", run.direct_ms), ("v", run.via_ms)):
            out.extend((t - t0) / 1e6 for t0, t in got[key] if t0 >= t_measure)
    finally:
        for s in socks:
            s.close(0)
        netsim.stop(5, signal.SIGINT)  # it writes its statistics as it stops
        netsim.close()
        ctx.destroy(linger=0)
    with contextlib.suppress(OSError, ValueError):
        run.netsim_stats = json.loads(stats_path.read_text())
    for path in (stats_path, workdir / "netsim.log"):
        path.unlink(missing_ok=True)
    workdir.rmdir()
    return run


def _sleep_until(t_ns: int) -> None:
    """Sleep to about 0.3 ms before ``t_ns``, then spin (sleep wakes late on a VM)."""
    left = t_ns - time.monotonic_ns()
    if left > 300_000:
        time.sleep((left - 300_000) / 1e9)
    while time.monotonic_ns() < t_ns:
        pass
