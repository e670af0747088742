"""``deepxpalm record``: keep every robot's stream from the fabric or a robot, for analysis.

A recorder is a roster key with the role ``recorder``: it subscribes to the
whole telemetry of the robots it names (frames included), checks every
message with the codec (a bad one is counted, never written) and appends
the wire bytes to a file, each as ``<u64 receive ns><u32 length><bytes>``
(little-endian). It sends nothing, so it can never command a robot. On the
fabric (``mode = "fabric"``) it reads through the router with its recorder
certificate, every message of the robots it names (none dropped for a newer
one, as a node would).

With ``foxglove.enabled`` it also serves a session's recordings live to
Foxglove (``common/live_view/session_files.py``: the camera, the pads, the arm and the
palm as they are written, on the robot PC); that needs the ``foxglove`` extra.
"""

from __future__ import annotations

import argparse
import logging
import struct
import threading
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import zmq

from common.clocks.clock import now_ns
from common.config.typed import param
from common.errors import ConfigError
from common.fabric.session import FabricConfig
from common.keys.curve import SecurityConfig, check_endpoint, client_options
from common.logs import BurstLog
from common.process.command_line import (
    add_config_arguments,
    load_node_config,
    print_config,
    stop_on_signals,
    write_stats,
)
from common.process.sd_notify import Notifier
from common.recording.foxglove import FoxgloveLiveConfig
from common.wire.codec import MAX_MESSAGE_BYTES, MAX_NAME_LEN, DecodeError, decode_named
from common.wire.link_stats import SEQ_RESTART_GAP

log = logging.getLogger(__name__)

_RECORD = struct.Struct("<QI")


@dataclass
class RecorderConfig:
    telemetry_endpoint: str = param(
        "tcp://127.0.0.1:5555", "mode direct: a robot's telemetry endpoint (its link)"
    )
    robots: list[str] = param([], "robot names to record; empty = every one")
    output: Path | None = param(None, "append the wire messages here; unset = count only")
    security: SecurityConfig = param(
        SecurityConfig(), "mode direct, CURVE: our key pair and the robot's key"
    )
    mode: Literal["direct", "fabric"] = param(
        "direct",
        "direct: one robot's telemetry endpoint above; fabric: through a Zenoh router "
        "([recorder.fabric], docs/fabric.md), where robots must name each robot to record",
    )
    fabric: FabricConfig = param(FabricConfig(), "mode fabric: the router and our certificate")
    foxglove: FoxgloveLiveConfig = param(
        FoxgloveLiveConfig(), "a live view in Foxglove of a session being recorded; off by default"
    )


class StreamRecorder:
    """Subscribes, validates, counts per robot and topic, and writes what passed."""

    def __init__(self, config: RecorderConfig, ctx: zmq.Context | None = None) -> None:
        from common.wire.codec import check_robot_name, name_prefix

        self.config = config
        self._own_ctx = ctx is None
        self.ctx = ctx or zmq.Context()
        self.counters: Counter[str] = Counter()
        self._last_seq: dict[str, int] = {}
        self._bad = BurstLog(log, "recorder: rejected message")
        self._out = open(config.output, "ab") if config.output else None  # noqa: SIM115
        self.session = self.inbox = self.sock = None
        if config.mode == "fabric":
            self._open_fabric(config)
            return
        check_endpoint(config.telemetry_endpoint, config.security)
        self.sock = self.ctx.socket(zmq.SUB)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.setsockopt(zmq.RCVHWM, 10000)
        self.sock.setsockopt(zmq.MAXMSGSIZE, MAX_MESSAGE_BYTES + 1 + MAX_NAME_LEN)
        for opt, value in client_options(config.security).items():
            self.sock.setsockopt(opt, value)
        self.sock.connect(config.telemetry_endpoint)
        names = [check_robot_name(r) for r in config.robots]
        for name in names or [b""]:
            for topic in (b"STIM", b"FRAM", b"HBRT") if name else (b"",):
                self.sock.setsockopt(zmq.SUBSCRIBE, name_prefix(topic, name))

    def _open_fabric(self, config: RecorderConfig) -> None:
        from common.fabric import keyexprs
        from common.fabric.link import FabricSubscriber
        from common.fabric.session import member_name, open_member_session

        if not config.robots:
            raise ConfigError(
                "recorder mode 'fabric' needs robots: the router lets a recorder read each "
                "robot it knows by exact key, never every robot by a wildcard"
            )
        where = "recorder fabric"
        member = member_name(config.fabric, None, where)
        self.session = open_member_session(config.fabric, member, where, "recorder")
        kinds = ("stimulus", "frame", "heartbeat")
        keys = tuple(keyexprs.robot_key(r, k) for r in config.robots for k in kinds)
        self.inbox = FabricSubscriber(
            self.session, keys, expect_name=None, queue=10000, latest_value=False
        )

    def run(self, stop: threading.Event, duration_s: float | None = None) -> None:
        t_end = None if duration_s is None else now_ns() + round(duration_s * 1e9)
        try:
            while not stop.is_set() and (t_end is None or now_ns() < t_end):
                if self.inbox is not None:
                    if self.inbox.poll(0.1):
                        for t_recv, data in self.inbox.drain_raw():
                            self.take(data, t_recv)
                    continue
                if not self.sock.poll(100):
                    continue
                while self.sock.get(zmq.EVENTS) & zmq.POLLIN:
                    data = self.sock.recv(zmq.NOBLOCK)
                    self.take(data, now_ns())
        finally:
            self.close()

    def take(self, data: bytes, t_recv_ns: int) -> None:
        try:
            name, msg = decode_named(data)
        except DecodeError as e:
            self.counters["rejected"] += 1
            self._bad(str(e))
            return
        stream = f"{name.decode() or '-'}_{type(msg).TOPIC.decode()}"
        if stream not in self.counters:  # what an operator checks first: is it recording?
            log.info("recorder: recording %s from its first message", stream)
        self.counters[stream] += 1
        self._count_gap(stream, getattr(msg, "seq", None))
        if self._out is not None:
            self._out.write(_RECORD.pack(t_recv_ns, len(data)) + data)

    def _count_gap(self, stream: str, seq: int | None) -> None:
        """``<stream>_lost``: messages missing from a sender's ``seq`` (one up per message).

        A step back or a jump past ``SEQ_RESTART_GAP`` is the sender restarting,
        not a loss; a recording that lost nothing shows no ``_lost`` key at all.
        """
        if not isinstance(seq, int):
            return
        last = self._last_seq.get(stream)
        self._last_seq[stream] = seq
        if last is not None and 1 < seq - last <= SEQ_RESTART_GAP:
            self.counters[f"{stream}_lost"] += seq - last - 1

    def stats(self) -> dict[str, float]:
        return {k: float(v) for k, v in self.counters.items()}

    def close(self) -> None:
        if self._out is not None:
            self._out.close()
            self._out = None
        if self.inbox is not None:
            from common.fabric.session import close_session

            self.inbox.close()
            close_session(self.session)
            self.inbox = None
        if self.sock is not None:
            self.sock.close(0)
        if self._own_ctx:
            self.ctx.term()


def read_records(path: Path) -> Iterator[tuple[int, bytes, object]]:
    """(receive ns, robot name, message) for every whole record of a recorder's file.

    Stops quietly where the file ends mid-record (a killed recorder); a record
    that does not decode raises ``DecodeError`` (the recorder wrote only valid ones).
    """
    with open(path, "rb") as f:
        while True:
            head = f.read(_RECORD.size)
            if len(head) < _RECORD.size:
                return
            t_recv_ns, length = _RECORD.unpack(head)
            data = f.read(length)
            if len(data) < length:
                return
            name, msg = decode_named(data)
            yield t_recv_ns, name, msg


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_config_arguments(
        parser, RecorderConfig, "recorder", example="telemetry_endpoint=tcp://192.168.1.20:5555"
    )


def run(args: argparse.Namespace) -> int:
    config = load_node_config(args, RecorderConfig, "recorder")
    if args.print_config:
        print_config(config, "recorder")
        return 0
    stop = stop_on_signals()
    live = None
    if config.foxglove.enabled:
        from common.live_view.session_files import LiveSource  # the foxglove extra, only when asked

        live = LiveSource(config.foxglove)
    recorder = StreamRecorder(config)
    # subscribed: systemd, or whoever started it, may count on every message from now on
    where = config.fabric.router_endpoint if config.mode == "fabric" else config.telemetry_endpoint
    said = {"source": where} | ({"foxglove": live.server.url} if live is not None else {})
    Notifier().ready(f"recording from {where}", said)
    thread = None
    if live is not None:
        thread = threading.Thread(
            target=live.run, args=(stop, args.duration), name="foxglove-live", daemon=True
        )
        thread.start()
    try:
        recorder.run(stop, args.duration)
    finally:
        stop.set()
        if thread is not None:
            thread.join(timeout=5)
        stats = recorder.stats()
        if live is not None:
            stats.update({f"foxglove_{k}": float(v) for k, v in live.counters.items()})
        write_stats(args.stats_file, stats)
    return 0
