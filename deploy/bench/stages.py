"""The latency budget: each stage of the loop, and the loop end to end in one process.

Stages are timed inline, one frame at a time through the whole chain, so
each stage runs with the caches the previous one left (as in the nodes),
not in a hot loop of its own. Every stage calls the code the nodes call:
the serial driver's parser and frame code, the classifier, the rendering
functions, the codec, ZeroMQ, the LinkGlide renderer and scservo_sdk's
sync-write builder.

End to end runs the nodes' own methods (``RobotNode.process`` and
``OperatorNode.receive`` / ``control_step``) over ZeroMQ's inproc transport,
from the bytes of a scan to the bytes of the servo packet.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from typing import Any

import numpy as np
import zmq

from common.clock import Rate, now_ns
from common.codec import decode, encode
from common.messages import Stimulus
from common.stimulus import is_contact, render_cells, sanitize_frame
from common.tactile import N_ANGLES, pattern_of
from common.transport import Link, Publisher, Subscriber
from deploy.bench.fixtures import (
    PacketBuilder,
    PacketServoBus,
    frame_set_of_at_least,
    scan_bytes,
    serial_sensor,
)
from deploy.bench.timing import summarize_ns
from operator_side.config import OperatorConfig
from operator_side.node import OperatorNode
from operator_side.renderer import LinkGlideRenderer
from operator_side.servos.calibration import LinkGlideCalibration
from robot_side.config import RobotConfig
from robot_side.node import RobotNode

log = logging.getLogger(__name__)

#: stage name -> what it covers, in loop order
STAGES: dict[str, str] = {
    "wire_decode": "serial bytes of one scan (2 packets, 424 B) -> 2 pad packets: "
    "StreamParser.feed (sync search, header, CRC)",
    "calibration": "pairing the pads, counts -> newtons, floor, saturation, mirror: "
    "SerialTactileSensor.accept_packet / _on_scan, then the conversion when the node takes it",
    "sanitize_contact": "sanitize_frame + is_contact (the node's prelude)",
    "classification": "predict_one: pattern and confidence of one frame (shipped model, "
    "default backend)",
    "render": "downsizing + masking: render_cells, the plain path since d31f386 (pad "
    "mean and 10x10 -> 3x3 as one 9x200 product, then mask and peak over nine numbers)",
    "frame_step": "the node's path in mask mode on the numba classifier: the three stages "
    "above (sanitize, contact, identical-frame test, classify, downsize, mask) as one "
    "compiled call (robot_side/compiled_step.py); timed on alternate frames",
    "encode": "Stimulus -> topic + msgpack (common.codec.encode)",
    "zmq_transit_tcp": "PUB.send -> SUB.recv over loopback TCP, one process",
    "decode": "bytes -> validated Stimulus (common.codec.decode)",
    "ik_3_linkages": "stimulus -> 3 contact points -> closed-form IK "
    "(LinkGlideRenderer.pose_for, the node's call)",
    "counts_rate_limit": "angles -> servo counts (counts_for: calibration, clip) + rate limit "
    "(step_goals), as the node calls them",
    "servo_packet": "limits check + the goal sync-write packet of 6 servos (SyncWritePacket, "
    "the bytes of scservo_sdk's GroupSyncWrite)",
    "encode_signed": "instead of encode, with the robot's link.signing_key_file: the built "
    "Stimulus packed and signed (Ed25519, cryptography); a pass of its own over the same "
    "stimuli",
    "decode_verified": "instead of decode, with the operator's link.robot_key_file: the "
    "signed bytes decoded and their signature verified; the same pass",
    "replay_window": "after decode_verified: the operator's telemetry gate "
    "(TelemetryGate.admit: the robot run, send time against the clock estimate, the "
    "seq window) on the verified stimulus; the same pass",
}
#: stages a signed stream adds or puts in place of encode and decode: not in the sum
SIGNED_STAGES = ("encode_signed", "decode_verified", "replay_window")
#: the plain path's stages, which the compiled frame step replaces
PLAIN_STAGES = ("sanitize_contact", "classification", "render")


def _recv(sub: zmq.Socket, timeout_ms: int = 2000) -> bytes:
    """A message that must come: waiting longer means it was lost, which is an error."""
    if not sub.poll(timeout_ms):
        raise RuntimeError(f"a message sent on {sub.getsockopt(zmq.LAST_ENDPOINT)!r} never came")
    return sub.recv()


def _pair(ctx: zmq.Context, endpoint: str) -> tuple[zmq.Socket, zmq.Socket]:
    """A PUB/SUB pair that has passed the slow-joiner window."""
    pub = ctx.socket(zmq.PUB)
    pub.setsockopt(zmq.LINGER, 0)
    pub.bind(endpoint)
    sub = ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.LINGER, 0)
    sub.setsockopt(zmq.SUBSCRIBE, b"")
    sub.connect(pub.getsockopt(zmq.LAST_ENDPOINT).decode())
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline:
        pub.send(b"ping")
        if sub.poll(10):
            sub.recv()
            break
    else:
        raise RuntimeError(f"ZeroMQ pair on {endpoint} never connected")
    while sub.poll(20):  # drop the extra pings
        sub.recv()
    return pub, sub


def stage_budget(
    n_frames: int, classifier: Any, seed: int = 1, pace_hz: float | None = None
) -> dict[str, Any]:
    """Median and p99 of every stage over ``n_frames`` frames of every pattern and level.

    ``pace_hz`` None runs the frames back to back (warm: each stage's code and
    data stay in the caches and branch predictors); a rate waits between
    frames as the node does between sensor frames, which on this machine
    makes every stage several times slower (the report shows both).
    """
    rate = Rate(pace_hz) if pace_hz else None
    fs = frame_set_of_at_least(n_frames, seed=seed)
    n = min(n_frames, len(fs))
    order = np.random.default_rng(seed).permutation(len(fs))[:n]
    warm = min(50 if rate is not None else 200, n)
    scans = [scan_bytes(fs.frames[k], seq) for seq, k in enumerate(np.r_[order[:warm], order])]
    cfg = RobotConfig()
    method, order = cfg.render.method, cfg.render.order
    sensor = serial_sensor()
    calibration = LinkGlideCalibration()
    renderer = LinkGlideRenderer(OperatorConfig().renderer, calibration)
    builder = PacketBuilder(calibration)
    ids = [int(i) for i in calibration.ids]
    ctx = zmq.Context()
    pub, sub = _pair(ctx, "tcp://127.0.0.1:*")
    from robot_side.node import compiled_step_for

    step = compiled_step_for(classifier, cfg.render)
    from common.signing import Signer

    signer = Signer.generate()
    gate = _believing_gate()
    built: list[Stimulus] = []  # the node path's stimuli, signed in a pass of their own
    times: dict[str, list[int]] = {name: [] for name in STAGES}
    total: list[int] = []  # frames through the node's path
    total_plain: list[int] = []  # frames through the plain path, when the node compiles
    current = list(renderer.retract_goals)
    clock = time.perf_counter_ns
    try:
        for j, data in enumerate(scans):
            i = j - warm
            # with a compiled step, frames alternate between it and the plain path, so
            # both are timed under the same conditions and neither warms the other
            compiled = step is not None and j % 2 == 1
            t0 = clock()
            packets = sensor.parse(data)
            t1 = clock()
            t_cap = now_ns()
            for packet in packets:
                sensor.accept_packet(packet, t_cap)
            sample = sensor.latest()
            t2 = clock()
            if compiled:
                step.forget()
                r = step.step(sample.frame)
                contact = r[0] != step.NO_CONTACT
                pattern = pattern_of(r[step.ANGLE], r[step.POSITION])
                at = step.PROBS
                p_angle = r[at + int(r[step.ANGLE])]
                p_position = r[at + N_ANGLES + int(r[step.POSITION])]
                confidence = min(max(p_angle * p_position, 0.0), 1.0)
                cells = r[step.CELLS :]
                t3 = t4 = t5 = clock()
            else:
                frame = sanitize_frame(sample.frame)
                contact = is_contact(frame)
                t3 = clock()
                prediction = classifier.predict_one(frame)
                pattern = prediction.pattern
                confidence = min(max(prediction.confidence, 0.0), 1.0)
                t4 = clock()
                cells = render_cells(frame, pattern, method=method, order=order)
                t5 = clock()
            stimulus = Stimulus(
                seq=i + warm + 1,
                t_send_ns=now_ns(),
                t_capture_ns=sample.t_capture_ns,
                frame_seq=sample.seq,
                mode="mask",
                contact=contact,
                stimulus=np.array(cells, np.float32).reshape(3, 3),
                pattern=pattern,
                confidence=confidence,
            )
            wire = encode(stimulus)  # encode: building the message and packing it
            t6 = clock()
            pub.send(wire)
            got = _recv(sub)
            t7 = clock()
            msg = decode(got)
            t8 = clock()
            pose = renderer.pose_for(msg.stimulus)
            t9 = clock()
            goal = calibration.counts_for(pose)
            nxt = renderer.step_goals(current, goal, 1.0)
            t10 = clock()
            builder.build(dict(zip(ids, nxt, strict=True)))  # as OperatorNode._write
            t11 = clock()
            current = renderer.retract_goals if i % 2 else nxt  # keep the steps non-trivial
            if i >= 0:
                built.append(stimulus)
            if rate is not None:
                rate.sleep()
            if i < 0:
                continue
            spans = {
                "wire_decode": t1 - t0,
                "calibration": t2 - t1,
                "encode": t6 - t5,
                "zmq_transit_tcp": t7 - t6,
                "decode": t8 - t7,
                "ik_3_linkages": t9 - t8,
                "counts_rate_limit": t10 - t9,
                "servo_packet": t11 - t10,
            }
            if compiled:
                spans["frame_step"] = t5 - t2
            else:
                spans.update(sanitize_contact=t3 - t2, classification=t4 - t3, render=t5 - t4)
            for name, dt in spans.items():
                times[name].append(dt)
            (total if compiled or step is None else total_plain).append(t11 - t0)
        # A signed stream's stages in a pass of their own over the same stimuli, so
        # their 300 us of crypto per frame do not cool the caches the node path meets.
        for stimulus in built:
            stimulus.session, stimulus.t_send_ns = gate.session, now_ns()  # sent now, this run
            t12 = clock()
            signed = encode(stimulus, b"", signer)
            t13 = clock()
            verified = decode(signed)
            t14 = clock()
            refusal = gate.admit(verified, now_ns())
            t15 = clock()
            if refusal is not None:
                raise RuntimeError(f"the telemetry gate refused a fresh stimulus: {refusal}")
            times["encode_signed"].append(t13 - t12)
            times["decode_verified"].append(t14 - t13)
            times["replay_window"].append(t15 - t14)
            if rate is not None:
                rate.sleep()
    finally:
        pub.close(0)
        sub.close(0)
        ctx.term()
    stages = {name: summarize_ns(times[name]).as_dict() for name in STAGES if times[name]}
    for name in stages:
        stages[name]["what"] = STAGES[name]
    node_path = [
        k for k in stages if (step is None or k not in PLAIN_STAGES) and k not in SIGNED_STAGES
    ]
    transit = transit_times(max(200, n // 4)) if rate is None else None
    return {
        "frames": n,
        "pace_hz": pace_hz,
        "classifier_backend": getattr(classifier, "backend", "?"),
        "method": method,
        "order": cfg.render.order,
        "stages": stages,
        "compiled_step": step is not None,
        "node_path": node_path,
        "sum_of_stage_medians_us": float(sum(stages[k]["median_us"] for k in node_path)),
        "instrumented_total": summarize_ns(total).as_dict(),
        "instrumented_total_plain": summarize_ns(total_plain).as_dict() if total_plain else None,
        "transit": transit,
    }


def _believing_gate() -> Any:
    """An operator's telemetry gate that believes one robot run, its clock offset known."""
    from common.clock_sync import ClockSync
    from common.messages import Heartbeat
    from operator_side.telemetry_gate import TelemetryGate

    clock = ClockSync()
    age_ns = round(OperatorConfig().link.max_telemetry_age_ms * 1e6)
    gate = TelemetryGate(clock, age_ns)
    t = now_ns()
    gate.heartbeat_sent(t)
    answer = Heartbeat(
        seq=1, t_send_ns=t + 1, node="robot", state="ok", echo_t_send_ns=t, session=0x5EED
    )
    if gate.admit(answer, t + 2) is not None:
        raise RuntimeError("the telemetry gate did not believe a run answering its heartbeat")
    clock.add_sample(t, t + 1, t + 1, t + 2)  # as the node feeds the clock that heartbeat
    return gate


def transit_times(n: int) -> dict[str, Any]:
    """One-way PUB -> SUB time of a stimulus-sized message per transport, one process."""
    msg = b"STIM" + bytes(200)
    out: dict[str, Any] = {}
    for name, endpoint in (
        ("inproc", "inproc://bench-transit"),
        # one path per process: two benches at once (a test run) must not share it
        ("ipc", f"ipc:///tmp/deepxpalm-bench-transit-{os.getpid()}.sock"),
        ("tcp_loopback", "tcp://127.0.0.1:*"),
    ):
        ctx = zmq.Context()
        try:
            pub, sub = _pair(ctx, endpoint)
        except zmq.ZMQError as e:  # ipc may be unavailable in a sandbox
            out[name] = {"error": str(e)}
            ctx.term()
            continue
        clock = time.perf_counter_ns
        samples = np.empty(n, dtype=np.int64)
        try:
            for i in range(-50, n):
                t = clock()
                pub.send(msg)
                _recv(sub)
                if i >= 0:
                    samples[i] = clock() - t
        finally:
            pub.close(0)
            sub.close(0)
            ctx.term()
            if endpoint.startswith("ipc://"):
                with contextlib.suppress(OSError):
                    os.unlink(endpoint[len("ipc://") :])
        out[name] = summarize_ns(samples).as_dict()
    return out


class InprocLoop:
    """Both nodes in one process on ZeroMQ's inproc transport, driven frame by frame.

    Each frame is forced all the way to a servo packet (the robot forgets
    its last stimulus, the operator its last write), so every sample is the
    path of a frame that changes what the palm feels; frames whose output
    does not change stop earlier and cost less (see the skipping section).
    """

    def __init__(self, classifier: Any, endpoint: str = "inproc://bench-e2e") -> None:
        self.ctx = zmq.Context()
        self.sensor = serial_sensor()
        self.robot = RobotNode(
            RobotConfig(),
            self.sensor,
            classifier=classifier,
            ctx=self.ctx,
            link=Link(pub=Publisher(self.ctx, endpoint, bind=True)),
        )
        self.bus = PacketServoBus()
        self.bus.connect()
        self.operator = OperatorNode(
            OperatorConfig(),
            self.bus,
            ctx=self.ctx,
            link=Link(sub=Subscriber(self.ctx, endpoint, bind=False, name="bench operator")),
        )
        self.period_ns = round(1e9 / OperatorConfig().renderer.control_rate_hz)
        self._join()

    def _join(self) -> None:
        sock = self.operator.sub.sock
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline:
            self.robot.pub.send_raw(b"HBRT")  # rejected by the codec: harmless, counted
            if sock.poll(10):
                break
        while sock.poll(10):
            sock.recv()

    def step(self, scan: bytes) -> tuple[int, int]:
        """One scan through both nodes: (wall ns from bytes to packet, CPU ns), or (-1, -1).

        The CPU time is this thread's (inproc moves messages without ZeroMQ's I/O
        thread, so it is all the work): wall time above it is time the thread
        waited for the core, which on a shared machine is other processes' doing.
        """
        robot, op = self.robot, self.operator
        robot.resend_next()
        op.rewrite_next()
        writes = self.bus.writes
        c0 = time.thread_time_ns()
        t0 = now_ns()
        self.sensor.feed(scan, t0)
        robot.process(self.sensor.latest())
        op.receive()
        op.control_step(now_ns(), self.period_ns)
        c1 = time.thread_time_ns()
        if self.bus.writes == writes:
            return -1, -1
        return self.bus.last_write_ns - t0, c1 - c0

    def close(self) -> None:
        self.robot.pub.close()
        self.operator.sub.close()
        self.ctx.term()


def end_to_end_inproc(
    n_frames: int, classifier: Any, seed: int = 2, pace_hz: float | None = None
) -> dict[str, Any]:
    """Frame bytes to servo packet through both nodes' code in one process.

    ``pace_hz``: wait between frames as a sensor paces them (see stage_budget).
    """
    rate = Rate(pace_hz) if pace_hz else None
    fs = frame_set_of_at_least(n_frames, seed=seed)
    n = min(n_frames, len(fs))
    order = np.random.default_rng(seed).permutation(len(fs))[:n]
    warm = min(50 if rate is not None else 200, n)
    scans = [scan_bytes(fs.frames[k], seq) for seq, k in enumerate(np.r_[order[:warm], order])]
    loop = InprocLoop(classifier)
    samples, cpu = [], []
    missing = 0
    try:
        for i, scan in enumerate(scans):
            dt, dc = loop.step(scan)
            if rate is not None:
                rate.sleep()
            if i < warm:
                continue
            if dt < 0:
                missing += 1
            else:
                samples.append(dt)
                cpu.append(dc)
    finally:
        loop.close()
    s = summarize_ns(samples).as_dict()
    s["frames_without_packet"] = missing
    s["transport"] = "inproc"
    s["pace_hz"] = pace_hz
    s["cpu"] = summarize_ns(cpu).as_dict()
    s["cpu"]["what"] = "the thread's CPU time per frame (thread_time_ns), same frames"
    return s
