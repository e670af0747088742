"""End to end across two processes over loopback TCP: frame bytes here, servo packet there.

This process plays the robot PC (the serial driver's parser and frame code,
then ``RobotNode.process`` publishing on TCP); a child process plays the
operator PC (``OperatorNode.receive`` and ``palm_step`` writing to a bus
that builds the real sync-write packet). Both read the same
``CLOCK_MONOTONIC``, so the child measures from the stimulus's
``t_capture_ns`` (taken before the scan's bytes were parsed) to the moment
the packet bytes exist: no clock-offset estimate is involved.

Frames are paced at a sensor-like rate, so each one meets sleeping
processes, as in the field. Every frame is forced to a packet, as in the
inproc loop.

As a bench section: end to end across two processes over loopback TCP, the
machine's floor beside it.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from common.clocks.clock import Rate, now_ns
from common.process.realtime import ONE_THREAD_POOLS
from common.process.sd_notify import Notifier
from deploy.units.catalogue import UnitSpec
from deploy.units.service import Service
from harness.bench.fmt import num, results_of
from harness.bench.section import Context, Results, Section, Verdict
from harness.bench.timing import summarize_ns

log = logging.getLogger(__name__)

#: wire sequence numbers of timed frames start here; warm-up frames stay below
TIMED_SEQ_START = 1_000_000


#: the bench's peer: an operator-side program of the harness (``python -m harness.bench.e2e_tcp``)
PEER = UnitSpec(
    "bench-peer",
    (),
    "the bench's operator side over TCP",
    "nothing bound: READY=1 once its subscription hears the robot (ZeroMQ's slow joiner)",
)


def _start_peer(argv: list[str], out_path: Path) -> Service:
    peer = Service(
        PEER,
        argv,
        out_path.with_suffix(".log"),
        env={**os.environ, **ONE_THREAD_POOLS},
        module="harness.bench.e2e_tcp",
    )
    peer.start()
    return peer


def _wait_joined(peer: Service, timeout_s: float, tick: Any) -> None:
    """Until the peer says READY=1 (it hears us), calling ``tick()`` (a warm-up message)."""
    deadline = time.monotonic() + timeout_s
    while peer.ready is None:
        if time.monotonic() > deadline or not peer.alive():
            peer.wait_ready(0)  # NotReady, with the peer's log
        tick()


def _end_peer(peer: Service, out_path: Path) -> None:
    peer.stop(0)
    peer.close()
    out_path.with_suffix(".log").unlink(missing_ok=True)


def end_to_end_tcp(
    n_frames: int,
    rate_hz: float,
    classifier: Any,
    cpu: int | None,
    seed: int = 3,
    peer_cpu: int | None = None,
) -> dict[str, Any]:
    """Median and p99 from scan bytes (this process) to servo packet (the child).

    The child is pinned to ``peer_cpu`` (default: ``cpu``, this process's core).
    """
    peer_cpu = cpu if peer_cpu is None else peer_cpu
    import zmq

    from common.wire.transport import Link, Publisher
    from harness.bench.fixtures import frame_set_of_at_least, scan_bytes, serial_sensor
    from robot_side.node import RobotNode
    from robot_side.node.config import RobotConfig

    fs = frame_set_of_at_least(n_frames, seed=seed)
    order = np.random.default_rng(seed).permutation(len(fs))
    frames = fs.frames[order]
    ctx = zmq.Context()
    sensor = serial_sensor()
    pub = Publisher(ctx, "tcp://127.0.0.1:*", bind=True)
    robot = RobotNode(RobotConfig(), sensor, classifier=classifier, ctx=ctx, link=Link(pub=pub))
    out_path = Path(f"/tmp/deepxpalm-bench-tcp-{os.getpid()}.json")
    cmd = ["--endpoint", pub.endpoint, "--count", str(n_frames), "--out", str(out_path)]
    if peer_cpu is not None:
        cmd += ["--cpu", str(peer_cpu)]
    peer = _start_peer(cmd, out_path)
    seq = [0]

    def feed(wire_seq: int, frame: np.ndarray) -> None:
        robot.resend_next()  # force a publish: every frame reaches the palm
        sensor.feed(scan_bytes(frame, wire_seq), now_ns())
        robot.process(sensor.latest())

    def warm() -> None:
        seq[0] += 1
        feed(seq[0], frames[seq[0] % len(frames)])
        time.sleep(0.01)

    try:
        _wait_joined(peer, 80.0, tick=warm)  # its imports, then our first messages
        # Encoding the scan is the board's work, not the robot's: do it before the clock starts.
        scans = [scan_bytes(frames[i % len(frames)], TIMED_SEQ_START + i) for i in range(n_frames)]
        rate = Rate(rate_hz)
        for scan in scans:
            robot.resend_next()
            sensor.feed(scan, now_ns())
            robot.process(sensor.latest())
            rate.sleep()
        peer.popen.wait(timeout=30)  # it writes what it measured and ends
        result = json.loads(out_path.read_text())
    finally:
        _end_peer(peer, out_path)
        out_path.unlink(missing_ok=True)
        pub.close()
        ctx.term()
    s = summarize_ns(result["latencies_ns"]).as_dict()
    s["received"] = len(result["latencies_ns"])
    s["sent"] = n_frames
    splits = np.array(result.get("splits_ns") or [[0, 0, 0]], dtype=np.int64)
    s["split"] = {
        name: summarize_ns(splits[:, k]).as_dict()
        for k, name in enumerate(("robot", "transit", "operator"))
    }
    s["rate_hz"] = rate_hz
    s["transport"] = "tcp loopback, two processes"
    s["robot_core"] = cpu
    s["operator_core"] = peer_cpu
    return s


def loopback_floor(
    n_frames: int, rate_hz: float, cpu: int | None, peer_cpu: int | None = None
) -> dict[str, Any]:
    """The same two processes, pinning and pacing with no work: what this machine allows.

    A stimulus-sized message carries its send time; the child takes it off the
    socket and notes the time. On an idle machine this is ZeroMQ and two
    wake-ups; on a loaded one it is mostly the wait for a core, which no code
    of ours can shorten.
    """
    import struct

    import zmq

    peer_cpu = cpu if peer_cpu is None else peer_cpu
    ctx = zmq.Context()
    pub = ctx.socket(zmq.PUB)
    pub.setsockopt(zmq.LINGER, 0)
    pub.bind("tcp://127.0.0.1:*")
    endpoint = pub.getsockopt(zmq.LAST_ENDPOINT).decode()
    out_path = Path(f"/tmp/deepxpalm-bench-floor-{os.getpid()}.json")
    cmd = ["--floor", "--endpoint", endpoint, "--count", str(n_frames), "--out", str(out_path)]
    if peer_cpu is not None:
        cmd += ["--cpu", str(peer_cpu)]
    peer = _start_peer(cmd, out_path)
    pad = bytes(192)

    def send(seq: int) -> None:
        pub.send(b"STIM" + struct.pack("<qq", seq, now_ns()) + pad)

    try:
        warm = [0]

        def tick() -> None:
            warm[0] += 1
            send(-warm[0])
            time.sleep(0.01)

        _wait_joined(peer, 80.0, tick=tick)  # its imports, then our first messages
        rate = Rate(rate_hz)
        for i in range(n_frames):
            send(i)
            rate.sleep()
        peer.popen.wait(timeout=30)  # it writes what it measured and ends
        result = json.loads(out_path.read_text())
    finally:
        _end_peer(peer, out_path)
        out_path.unlink(missing_ok=True)
        pub.close(0)
        ctx.term()
    s = summarize_ns(result["latencies_ns"]).as_dict()
    s["received"] = len(result["latencies_ns"])
    s["rate_hz"] = rate_hz
    s["robot_core"] = cpu
    s["operator_core"] = peer_cpu
    return s


def _floor_peer(args: argparse.Namespace) -> int:
    import struct

    import zmq

    ctx = zmq.Context()
    sub = ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.LINGER, 0)
    sub.setsockopt(zmq.SUBSCRIBE, b"")
    sub.connect(args.endpoint)
    latencies: list[int] = []
    joined = False
    last = time.monotonic()
    while len(latencies) < args.count and time.monotonic() - last < 5.0:
        if not sub.poll(200):
            continue
        data = sub.recv()
        t = now_ns()
        last = time.monotonic()
        seq, t0 = struct.unpack_from("<qq", data, 4)
        if not joined:
            joined = True
            Notifier().ready("joined")  # it hears the bench: the timed messages may start
        if seq >= 0:
            latencies.append(t - t0)
    Path(args.out).write_text(json.dumps({"latencies_ns": latencies}))
    sub.close(0)
    ctx.term()
    return 0


def _peer(args: argparse.Namespace) -> int:
    """The operator side: count ``--count`` timed stimuli, then write their latencies."""
    if args.cpu is not None:
        os.sched_setaffinity(0, {args.cpu})
    import zmq

    from common.wire.transport import Link, Subscriber
    from harness.bench.fixtures import PacketServoBus
    from operator_side.node import OperatorNode
    from operator_side.node.config import OperatorConfig

    class StampedSubscriber(Subscriber):
        """Keeps the newest message's receive time, to split the latency at the socket."""

        last_recv_ns = 0

        def drain(self, max_messages: int = 1024) -> list[tuple[Any, int]]:
            out = super().drain(max_messages)
            if out:
                self.last_recv_ns = out[-1][1]
            return out

    bus = PacketServoBus()
    bus.connect()
    ctx = zmq.Context()
    sub = StampedSubscriber(ctx, args.endpoint, bind=False, name="bench peer")
    node = OperatorNode(OperatorConfig(), bus, ctx=ctx, link=Link(sub=sub))
    period_ns = round(1e9 / node.config.renderer.palm_step_rate_hz)
    latencies: list[int] = []
    splits: list[tuple[int, int, int]] = []
    joined = False
    last_msg = time.monotonic()
    while len(latencies) < args.count and time.monotonic() - last_msg < 5.0:
        if not sub.poll(0.2):
            continue
        node.rewrite_next()  # force the packet, as the robot side forces the stimulus
        writes = bus.writes
        if not node.receive():
            continue
        node.palm_step(now_ns(), period_ns)
        last_msg = time.monotonic()
        stim = node.last_stimulus
        if not joined:
            joined = True
            Notifier().ready("joined")  # it hears the bench: the timed messages may start
        if stim is not None and stim.frame_seq > TIMED_SEQ_START and bus.writes > writes:
            latencies.append(bus.last_write_ns - stim.t_capture_ns)
            splits.append(
                (
                    stim.t_send_ns - stim.t_capture_ns,  # robot: bytes in to message out
                    sub.last_recv_ns - stim.t_send_ns,  # ZeroMQ over TCP, both I/O threads
                    bus.last_write_ns - sub.last_recv_ns,  # operator: decode to packet
                )
            )
    Path(args.out).write_text(json.dumps({"latencies_ns": latencies, "splits_ns": splits}))
    sub.close()
    ctx.term()
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="operator-side peer of deepxpalm bench (TCP)")
    parser.add_argument("--endpoint", required=True)
    parser.add_argument("--count", type=int, required=True)
    parser.add_argument("--out", required=True)
    parser.add_argument("--cpu", type=int)
    parser.add_argument("--floor", action="store_true", help="no work: the machine's floor")
    args = parser.parse_args(argv)
    if args.floor:
        if args.cpu is not None:
            os.sched_setaffinity(0, {args.cpu})
        return _floor_peer(args)
    return _peer(args)


#: the issue's target for the two-process chain
MEDIAN_TARGET_US = 1000.0


@dataclass(frozen=True)
class TcpSizes:
    tcp_frames: int
    tcp_rate_hz: float


SIZES = {
    "full": TcpSizes(tcp_frames=3000, tcp_rate_hz=120.0),
    "quick": TcpSizes(tcp_frames=400, tcp_rate_hz=200.0),
    "smallest": TcpSizes(tcp_frames=50, tcp_rate_hz=500.0),
}


def measure(ctx: Context, sizes: TcpSizes) -> dict[str, Any]:
    """Both processes on the bench's core, then the operator on another when there is one."""
    from harness.bench.timing import original_affinity

    n, rate, core = sizes.tcp_frames, sizes.tcp_rate_hz, ctx.core
    out = end_to_end_tcp(n, rate, ctx.classifier, core)
    out["floor"] = loopback_floor(n, rate, core)
    others = sorted(original_affinity() - {core})
    if others:  # two machines in the field: the operator on a core of its own
        apart = end_to_end_tcp(n, rate, ctx.classifier, core, peer_cpu=others[0])
        apart["floor"] = loopback_floor(n, rate, core, peer_cpu=others[0])
        out["operator_on_other_core"] = apart
    return out


def verdicts(results: Results) -> list[Verdict]:
    """Judged with a core each (two machines in the field); both on one core given beside it."""
    tcp = results_of(results, "e2e_tcp")
    apart = None if tcp is None else tcp.get("operator_on_other_core")
    judged = apart or tcp
    measured = None
    if judged is not None:
        measured = (
            f"median {num(judged['median_us'])} us, p99 {num(judged['p99_us'])} us "
            + ("(a core each)" if apart else "(one core)")
            + f"; this machine's floor with no work: median "
            f"{num(judged.get('floor', {}).get('median_us'))} us"
        )
        if apart:
            measured += (
                f". Both on one core: median {num(tcp['median_us'])} us, "
                f"p99 {num(tcp['p99_us'])} us"
            )
    return [
        Verdict(
            "end to end, two processes, loopback TCP: median < "
            f"{MEDIAN_TARGET_US / 1000:g} ms (p99 reported)",
            measured,
            None if judged is None else judged["median_us"] < MEDIAN_TARGET_US,
        )
    ]


def markdown(results: Results) -> list[str]:
    """Nothing of its own: its rows are in the end-to-end table (the e2e_inproc section)."""
    return []


SECTION = Section(
    name="e2e_tcp",
    title="End to end: frame bytes to servo packet",
    sizes=SIZES,
    measure=measure,
    markdown=markdown,
    verdicts=verdicts,
    quick=False,
)


if __name__ == "__main__":
    sys.exit(main())
