"""The latency budget: each stage of the loop, one frame at a time.

Stages are timed inline, one frame at a time through the whole chain, so
each stage runs with the caches the previous one left (as in the nodes),
not in a hot loop of its own. Every stage calls the code the nodes call:
the serial driver's parser and frame code, the classifier, the rendering
functions, the codec, ZeroMQ, the LinkGlide renderer and scservo_sdk's
sync-write builder.

As a bench section: the latency budget, stage by stage, back to back and paced at the sensor's rate.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zmq

from common.clocks.clock import Rate, now_ns
from common.tactile.contract import N_ANGLES, pattern_of
from common.tactile.stimulus import is_contact, render_cells, sanitize_frame
from common.wire.codec import decode, encode
from common.wire.messages import Stimulus
from harness.bench.fixtures import (
    PacketBuilder,
    frame_set_of_at_least,
    scan_bytes,
    serial_sensor,
)
from harness.bench.fmt import IMG_DIR, num, pyplot, results_of, save_figure, table
from harness.bench.section import Context, Results, Section
from harness.bench.timing import summarize_ns
from operator_side.node.config import OperatorConfig
from operator_side.palm.renderer import LinkGlideRenderer
from operator_side.servos.calibration import LinkGlideCalibration
from robot_side.node.config import RobotConfig

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
    "render": "downsizing + masking: render_cells, the plain path (pad mean and 10x10 -> "
    "3x3 as one 9x200 product, then mask and peak over nine numbers)",
    "frame_step": "the node's path in mask mode on the numba classifier: the three stages "
    "above (sanitize, contact, identical-frame test, classify, downsize, mask) as one "
    "compiled call (robot_side/node/compiled_step.py); timed on alternate frames",
    "encode": "Stimulus -> topic + msgpack (common.wire.codec.encode)",
    "zmq_transit_tcp": "PUB.send -> SUB.recv over loopback TCP, one process",
    "decode": "bytes -> validated Stimulus (common.wire.codec.decode)",
    "ik_3_linkages": "stimulus -> 3 contact points -> closed-form IK "
    "(LinkGlideRenderer.pose_for, the node's call)",
    "counts_rate_limit": "angles -> servo counts (counts_for: calibration, clip) + rate limit "
    "(step_goals), as the node calls them",
    "servo_packet": "limits check + the goal sync-write packet of 6 servos (SyncWritePacket, "
    "the bytes of scservo_sdk's GroupSyncWrite)",
    "encode_signed": "instead of encode, with the robot's link.signing_key_file: the built "
    "Stimulus packed and signed (Ed25519, libsodium); a pass of its own over the same "
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
    from common.wire.signing import Signer

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
    from common.clocks.clock_sync import ClockSync
    from common.wire.messages import Heartbeat
    from operator_side.node.telemetry_gate import TelemetryGate

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


TITLE = "Latency budget per stage"


@dataclass(frozen=True)
class StagesSizes:
    stage_frames: int  # back to back
    stage_paced_frames: int
    pace_hz: float  # the sensor's rate the paced runs wait for


SIZES = {
    "full": StagesSizes(stage_frames=20000, stage_paced_frames=1800, pace_hz=120.0),
    "quick": StagesSizes(stage_frames=600, stage_paced_frames=120, pace_hz=120.0),
    "smallest": StagesSizes(stage_frames=100, stage_paced_frames=30, pace_hz=500.0),
}


def measure(ctx: Context, sizes: StagesSizes) -> dict[str, Any]:
    """Both runs; the paced medians and the loopback transit go to the context for others."""
    out = stage_budget(sizes.stage_frames, ctx.classifier)
    out["paced"] = stage_budget(sizes.stage_paced_frames, ctx.classifier, pace_hz=sizes.pace_hz)
    # the costs a frame pays in the field (paced), for the savings and the scale model
    ctx.stage_medians_us = {k: v["median_us"] for k, v in out["paced"]["stages"].items()}
    ctx.tcp_transit_us = out.get("transit", {}).get("tcp_loopback", {}).get("median_us", 0.0)
    return out


def markdown(results: Results) -> list[str]:
    s = results_of(results, "stages")
    if s is None:
        return ["", f"## {TITLE}", "", "Not run."]
    paced = s.get("paced") or {}
    pst = paced.get("stages", {})
    rate = paced.get("pace_hz")
    out = [
        "",
        f"## {TITLE}",
        "",
        f"Every frame is taken through the whole chain one at a time, so each stage meets "
        f"the caches the one before left. **Back to back**: {s['frames']:,} frames with no "
        f"pause. **Paced**: {num(paced.get('frames'))} frames at {num(rate, 0)} Hz, waiting "
        "between frames as the node waits for the sensor. Classifier backend "
        f"`{s['classifier_backend']}`, `{s['method']}` downsizing, `{s['order']}`. "
        "Microseconds, one core.",
        "",
    ]
    if s.get("compiled_step"):
        out += [
            "The node runs `frame_step` (one compiled call) where the plain path runs "
            "`sanitize_contact`, `classification` and `render`; frames alternate between the "
            "two, so each row has half the frames and both paths meet the same conditions. The "
            "plain rows are what `render.compiled_step = false` (or another classifier "
            "backend) costs; sums and totals below are the node's path.",
            "",
        ]
    out += table(
        [
            "stage",
            "back to back: median",
            "p99",
            f"paced at {num(rate, 0)} Hz: median",
            "p99",
            "what",
        ],
        [
            [
                f"`{k}`",
                num(v["median_us"]),
                num(v["p99_us"]),
                num(pst.get(k, {}).get("median_us")),
                num(pst.get(k, {}).get("p99_us")),
                v["what"],
            ]
            for k, v in s["stages"].items()
        ],
        "|---|---:|---:|---:|---:|---|",
    )
    tot = s["instrumented_total"]
    ptot = paced.get("instrumented_total", {})
    plain, pplain = s.get("instrumented_total_plain"), paced.get("instrumented_total_plain")
    plain_note = ""
    if plain and pplain:
        plain_note = (
            f" (the plain path's frames: median {num(plain['median_us'])} / p99 "
            f"{num(plain['p99_us'])} us back to back, median {num(pplain['median_us'])} / p99 "
            f"{num(pplain['p99_us'])} us paced)"
        )
    out += [
        "",
        f"Sum of the stage medians: {num(s['sum_of_stage_medians_us'])} us back to back, "
        f"{num(paced.get('sum_of_stage_medians_us'))} us paced; the instrumented chain end to "
        f"end: median {num(tot['median_us'])} / p99 {num(tot['p99_us'])} us back to back, "
        f"median {num(ptot.get('median_us'))} / p99 {num(ptot.get('p99_us'))} us paced"
        f"{plain_note}.",
        "",
        "**The same code costs several times more when frames are paced.** Between two "
        "frames the core runs other code (here other processes; on the robot PC the node's "
        "own threads), which evicts the caches and retrains the branch predictors an "
        "interpreter leans on (see Conditions: the first IK call after a frame period's gap "
        "costs many times a warm one, even when the gap spins on the same core). Back-to-back "
        "numbers are what a micro-benchmark shows; paced numbers are what a frame costs in "
        "the field, so the verdicts, the savings and the scale model below use them.",
        "",
        "One-way PUB to SUB in one process (a 204-byte message, back to back):",
        "",
    ]
    rows = []
    for name, t in (s.get("transit") or {}).items():
        if "error" in t:
            rows.append([name, "n/a", "n/a"])
        else:
            rows.append([name, num(t["median_us"]), num(t["p99_us"])])
    out += table(["transport", "median (us)", "p99 (us)"], rows, "|---|---:|---:|")
    out += ["", f"![stage budget]({IMG_DIR}/bench_stages.png)"]
    return out


def figure(result: dict[str, Any], path: Path) -> Path:
    plt = pyplot()
    names = list(result["stages"])
    paced = (result.get("paced") or {}).get("stages", {})
    series = [
        ("back to back, median", [result["stages"][n]["median_us"] for n in names], "#4c72b0"),
    ]
    if paced:
        rate = result["paced"]["pace_hz"]
        series.append(
            (
                f"paced {rate:g} Hz, median",
                [paced.get(n, {}).get("median_us", float("nan")) for n in names],
                "#dd8452",
            )
        )
        series.append(
            (
                f"paced {rate:g} Hz, p99",
                [paced.get(n, {}).get("p99_us", float("nan")) for n in names],
                "#f2c8a8",
            )
        )
    fig, ax = plt.subplots(figsize=(8.5, 5))
    h = 0.8 / len(series)
    for k, (label, values, color) in enumerate(series):
        ax.barh(
            [i - 0.4 + h * (k + 0.5) for i in range(len(names))],
            values,
            height=h,
            label=label,
            color=color,
        )
    ax.set_yticks(list(range(len(names))), names)
    ax.invert_yaxis()
    ax.set_xscale("log")
    ax.set_xlabel("microseconds (one core)")
    ax.set_title("latency budget per stage")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, axis="x", which="both")
    return save_figure(fig, path)


SECTION = Section(
    name="stages",
    title=TITLE,
    sizes=SIZES,
    measure=measure,
    markdown=markdown,
    figure=figure,
)
