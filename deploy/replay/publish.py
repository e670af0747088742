"""A recording's stimuli (and frames) sent again at their recorded pace (``--publish``).

Fresh timestamps, and heartbeats that keep the current stimulus confirmed,
so a live operator node or a dashboard can be driven from a recording.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from pathlib import Path

import numpy as np

from common.errors import ConfigError
from common.tactile.contract import SATURATION_N
from common.wire.codec import DecodeError, decode, encode
from common.wire.messages import Heartbeat, Stimulus, TactileFrame

log = logging.getLogger(__name__)


def publish(
    path: Path,
    endpoint: str,
    *,
    speed: float = 1.0,
    stop: threading.Event | None = None,
    wait_subscriber_s: float = 5.0,
    heartbeat_rate_hz: float = 20.0,
    frame_rate_hz: float = 15.0,
) -> dict[str, int]:
    """Send the recorded stimuli (and frames) again at their recorded pace."""
    import zmq

    from common.clocks.clock import now_ns
    from common.keys.curve import SecurityConfig, check_endpoint
    from common.recording.mcap_recorder import read_recording

    if not speed > 0:
        raise ConfigError(f"--speed must be positive, not {speed}")
    check_endpoint(endpoint, SecurityConfig())  # plain TCP: loopback only
    stop = stop or threading.Event()
    ctx = zmq.Context()
    sock = ctx.socket(zmq.XPUB)  # a PUB that also hears subscriptions: no slow-joiner loss
    sock.setsockopt(zmq.LINGER, 0)
    sent = collections.Counter()
    try:
        sock.bind(endpoint)
        if sock.poll(int(wait_subscriber_s * 1000)):
            sock.recv()  # the subscription itself
            time.sleep(0.05)
        else:
            log.warning(
                "no subscriber on %s after %.0f s; sending anyway", endpoint, wait_subscriber_s
            )
        hb_period = round(1e9 / heartbeat_rate_hz)
        frame_period = round(1e9 / frame_rate_hz) if frame_rate_hz > 0 else None
        t0_rec: int | None = None
        t0 = now_ns()
        next_hb = t0
        next_frame = t0
        hb_seq = frame_msg_seq = 0
        current: Stimulus | None = None

        def heartbeats_until(deadline: int) -> None:
            nonlocal next_hb, hb_seq
            while not stop.is_set():
                now = now_ns()
                if now >= deadline:
                    return
                if now >= next_hb:
                    hb_seq += 1
                    hb = Heartbeat(
                        seq=hb_seq,
                        t_send_ns=now,
                        node="robot",
                        state="ok",
                        stimulus_seq=None if current is None else current.seq,
                        t_capture_ns=None if current is None else now,
                    )
                    sock.send(encode(hb), zmq.NOBLOCK)
                    sent["heartbeats"] += 1
                    next_hb = now + hb_period
                while sock.poll(0):
                    sock.recv()  # subscriptions coming and going
                time.sleep(max(0.0, min(deadline, next_hb) - now_ns()) / 1e9)

        for channel, t_ns, record in read_recording(path):
            if stop.is_set():
                break
            kind = channel.split("/", 1)[-1]
            if kind not in ("stimulus", "frame"):
                continue
            t0_rec = t_ns if t0_rec is None else t0_rec
            heartbeats_until(t0 + round((t_ns - t0_rec) / speed))
            now = now_ns()
            if kind == "stimulus":
                try:
                    msg = decode(record["wire"])
                except (DecodeError, KeyError, TypeError):
                    sent["undecodable"] += 1
                    continue
                if not isinstance(msg, Stimulus):
                    continue
                age = max(0, msg.t_send_ns - msg.t_capture_ns)
                msg.t_send_ns, msg.t_capture_ns = now, max(0, now - age)
                sock.send(encode(msg), zmq.NOBLOCK)
                current = msg
                sent["stimuli"] += 1
            elif frame_period is not None and now >= next_frame:
                frame_msg_seq += 1
                raw = np.nan_to_num(record["frame"])
                frame = np.clip(raw, 0.0, SATURATION_N).astype(np.float32)
                msg = TactileFrame(
                    seq=frame_msg_seq,
                    t_send_ns=now,
                    t_capture_ns=now,
                    frame_seq=int(record["frame_seq"]),
                    frame=frame,
                )
                sock.send(encode(msg), zmq.NOBLOCK)
                sent["frames"] += 1
                next_frame = now + frame_period
    finally:
        sock.close(0)
        ctx.term()
    return dict(sent)
