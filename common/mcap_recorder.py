"""Recording to MCAP, the log format Foxglove opens, in a form that survives ``kill -9``.

Format (docs/recording.md): one MCAP channel per ``common.recording.CHANNELS``
name, messages JSON with an inferred JSON Schema, because Foxglove plots
JSON channels without any plugin. NumPy arrays become nested lists and bytes
become base64 strings; the schema marks them (``x-numpy-dtype``,
``contentEncoding: base64``) so ``read_recording`` gives back the same
arrays and bytes. A record holding the wire bytes of a message (``wire``)
also gets its decoded fields (``decoded``), so a stimulus can be plotted.

Foxglove (``common/foxglove.py``): the camera's pictures and the log lines
are written as Foxglove's own types (``foxglove.CompressedImage``,
``foxglove.Log``), and the pads, the arm's and fingers' poses and the palm
as Foxglove views derived from the records, on channels of their own
marked ``deepxpalm.view_of`` that ``read_recording`` leaves out unless
asked, so old and new files read alike.

Durability: the nodes' threads only append to a bounded queue; one writer
thread serialises, and every ``flush_interval_s`` closes the MCAP chunk in
progress, writes it and fsyncs. A chunk is a length-prefixed, CRC-checked
record, so a file cut anywhere (a killed process, a full disk) holds every
chunk that was flushed before the cut, and ``read_recording`` reads them
without the footer and summary that only a clean ``close()`` writes.

Times: ``publish_time`` is the ``t_ns`` the node gave (its monotonic clock,
the clock of every timestamp in the records); ``log_time`` is that plus the
wall-clock offset measured once at open, so Foxglove shows real dates while
the offset between the two never jumps inside a file.
"""

from __future__ import annotations

import base64
import collections
import contextlib
import dataclasses
import json
import logging
import math
import os
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from mcap.records import Channel, Chunk, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType, Writer

from common import foxglove
from common.errors import DeepXPalmError
from common.logs import BurstLog
from common.recording import CHANNELS

log = logging.getLogger(__name__)

MESSAGE_ENCODING = "json"
SCHEMA_ENCODING = "jsonschema"
SCHEMA_PREFIX = "deepxpalm/"
LIBRARY = "deepxpalm McapRecorder"
ENC_KEY = "_enc"  # per-message encodings, only where the channel's schema does not say them
NONFINITE_KEY = "_nonfinite"  # paths of NaN/inf values written as null (a bug to look at)
VIEW_OF_KEY = "deepxpalm.view_of"  # channel metadata: a Foxglove view, and of which channel
_COMPRESSION = {
    "zstd": CompressionType.ZSTD,
    "lz4": CompressionType.LZ4,
    "none": CompressionType.NONE,
}


class RecordingError(DeepXPalmError):
    """A recording cannot be opened or read; the message names the file."""


# ------------------------------------------------------------------ encoding
def _to_json(value: Any, path: str, encs: dict[str, str], nonfinite: list[str]) -> Any:
    """A JSON-ready copy of ``value``; ``encs`` collects where bytes and arrays were."""
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, (int, np.integer)) and not isinstance(value, np.bool_):
        return int(value)
    if isinstance(value, (float, np.floating)):
        v = float(value)
        if math.isfinite(v):
            return v
        nonfinite.append(path)
        return None
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, (bytes, bytearray, memoryview)):
        encs[path] = "base64"
        return base64.b64encode(bytes(value)).decode("ascii")
    if isinstance(value, np.ndarray):
        encs[path] = value.dtype.str
        if value.dtype.kind == "f" and not np.isfinite(value).all():
            nonfinite.append(path)
            out = value.astype(object)
            out[~np.isfinite(value)] = None
            return out.tolist()
        return value.tolist()
    if isinstance(value, dict):
        return {
            str(k): _to_json(v, f"{path}.{k}" if path else str(k), encs, nonfinite)
            for k, v in value.items()
        }
    if isinstance(value, (list, tuple)):
        return [_to_json(v, f"{path}[]", {}, nonfinite) for v in value]
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return _to_json(dataclasses.asdict(value), path, encs, nonfinite)
    return str(value)


def _nan_for_none(value: Any) -> Any:
    if isinstance(value, list):
        return [_nan_for_none(v) for v in value]
    return math.nan if value is None else value


def _schema_of(value: Any, path: str, encs: dict[str, str]) -> dict[str, Any] | None:
    """JSON Schema of one converted value; None where nothing can be said (a null)."""
    enc = encs.get(path)
    if value is None:
        return None
    if isinstance(value, bool):
        return {"type": "boolean"}
    if isinstance(value, int):
        return {"type": "integer"}
    if isinstance(value, float):
        return {"type": "number"}
    if isinstance(value, str):
        if enc == "base64":
            return {"type": "string", "contentEncoding": "base64"}
        return {"type": "string"}
    if isinstance(value, list):
        out: dict[str, Any] = {"type": "array"}
        item = next((v for v in value if v is not None), None)
        item_schema = _schema_of(item, f"{path}[]", {}) if item is not None else None
        if item_schema is not None:
            out["items"] = item_schema
        if enc is not None:
            out["x-numpy-dtype"] = enc
        return out
    if isinstance(value, dict):
        props = {}
        for k, v in value.items():
            s = _schema_of(v, f"{path}.{k}" if path else k, encs)
            if s is not None:
                props[k] = s
        return {"type": "object", "properties": props}
    return None


def _encodings_in_schema(schema: dict[str, Any], path: str = "") -> dict[str, str]:
    """Where a channel's schema says bytes (base64) and arrays (their dtype) are."""
    out: dict[str, str] = {}
    if schema.get("contentEncoding") == "base64":
        out[path] = "base64"
    if "x-numpy-dtype" in schema:
        out[path] = schema["x-numpy-dtype"]
    for k, sub in schema.get("properties", {}).items():
        out.update(_encodings_in_schema(sub, f"{path}.{k}" if path else k))
    return out


def _restore(record: dict[str, Any], encs: dict[str, str]) -> None:
    """Turn base64 strings and nested lists back into bytes and arrays, in place."""
    for path, enc in encs.items():
        *parents, leaf = path.split(".")
        node: Any = record
        for key in parents:
            node = node.get(key) if isinstance(node, dict) else None
        if not isinstance(node, dict) or node.get(leaf) is None:
            continue
        value = node[leaf]
        try:
            if enc == "base64":
                node[leaf] = base64.b64decode(value)
            else:
                dtype = np.dtype(enc)
                if dtype.kind == "f":
                    value = _nan_for_none(value)
                node[leaf] = np.asarray(value, dtype=dtype)
        except (ValueError, TypeError):
            log.debug("cannot restore %s as %s; left as is", path, enc)


def _decoded_fields(wire: bytes) -> dict[str, Any]:
    """The fields of a wire message, for plotting; the codec's own validation applies."""
    from common.codec import DecodeError, decode  # the codec is only needed for "wire" records

    try:
        msg = decode(wire)
    except DecodeError as e:
        return {"error": f"{type(e).__name__}: {e}"}
    out: dict[str, Any] = {"type": type(msg).TYPE}
    for f in dataclasses.fields(msg):
        out[f.name] = getattr(msg, f.name)
    return out


# -------------------------------------------------------------------- writer
@dataclasses.dataclass
class _ChannelState:
    id: int
    encs: dict[str, str]
    seq: int = 0


class McapRecorder:
    """A ``Recorder`` writing MCAP; ``write`` is safe from any thread and never blocks on disk.

    Memory is bounded: at most ``max_queue`` records wait for the writer
    thread (beyond that they are dropped and counted, so a stalled disk
    cannot grow a node's memory) and at most one chunk (``flush_interval_s``
    of data, capped by ``chunk_size`` bytes) is held before it is written.
    The writer keeps one small index entry per chunk for the file's summary,
    about 0.9 kB, i.e. about 3 MB per hour at one chunk per second.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        flush_interval_s: float = 1.0,
        *,
        max_queue: int = 20_000,
        chunk_size: int = 1 << 20,
        compression: str = "zstd",
        fsync: bool = True,
        decode_wire: bool = True,
        metadata: dict[str, dict[str, str]] | None = None,
        foxglove_views: bool = True,
        log_level: int | None = None,
    ) -> None:
        if not flush_interval_s > 0:
            raise ValueError(f"flush_interval_s must be positive, not {flush_interval_s!r}")
        if compression not in _COMPRESSION:
            raise ValueError(f"compression must be one of {sorted(_COMPRESSION)}")
        self.path = Path(path)
        self.flush_interval_s = float(flush_interval_s)
        self.max_queue = int(max_queue)
        self._fsync = fsync
        self._decode_wire = decode_wire
        self._foxglove = foxglove_views
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file: BinaryIO = open(self.path, "wb")  # noqa: SIM115 (closed by the writer thread)
        except OSError as e:
            raise RecordingError(f"cannot open {self.path} for recording: {e}") from None
        self._writer = Writer(
            self._file, chunk_size=chunk_size, compression=_COMPRESSION[compression]
        )
        self._writer.start(profile="", library=LIBRARY)
        self.wall_offset_ns = time.time_ns() - time.monotonic_ns()
        self._writer.add_metadata(
            "deepxpalm.clock",
            {
                "wall_offset_ns": str(self.wall_offset_ns),
                "what": "log_time = publish_time + wall_offset_ns; publish_time is the "
                "recording node's monotonic clock (time.monotonic_ns)",
            },
        )
        for name, data in (metadata or {}).items():
            self._writer.add_metadata(name, {str(k): str(v) for k, v in data.items()})
        self._writer.flush()
        self._channels: dict[str, _ChannelState] = {}
        self._queue: collections.deque[tuple[Any, ...]] = collections.deque()
        self._cond = threading.Condition()
        self._closing = False
        self._closed = False
        self._failed: str | None = None
        self._drop_log = BurstLog(log, f"recorder {self.path.name}: record dropped")
        # counters (read by stats(); written under _cond or by the writer thread only)
        self.records_written = 0
        self.records_dropped = 0
        self.records_nonfinite = 0
        self.chunks_flushed = 0
        self.records_flushed = 0  # records on disk as of the latest chunk flush
        self.last_flush_ns: int | None = None
        self._thread = threading.Thread(
            target=self._run, name=f"mcap-recorder:{self.path.name}", daemon=True
        )
        self._thread.start()
        self._log_handler: _LogHandler | None = None
        if log_level is not None:
            self._log_handler = _LogHandler(self, log_level)
            logging.getLogger().addHandler(self._log_handler)

    # ------------------------------------------------------------ Recorder
    def write(self, channel: str, t_ns: int, record: dict[str, Any]) -> None:
        """Queue one record; arrays are copied so the caller may reuse its buffers."""
        item = {k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in record.items()}
        with self._cond:
            if self._closing or self._failed is not None:
                self.records_dropped += 1
                return
            if len(self._queue) >= self.max_queue:
                self.records_dropped += 1
                self._drop_log(f"queue full ({self.max_queue} records); is the disk stalled?")
                return
            self._queue.append(("msg", channel, int(t_ns), item))
            if len(self._queue) == self.max_queue // 2:
                self._cond.notify()

    def close(self) -> None:
        """Write everything queued, the summary and the footer; idempotent."""
        if self._log_handler is not None:
            logging.getLogger().removeHandler(self._log_handler)
        with self._cond:
            if self._closed:
                return
            self._closing = True
            self._cond.notify()
        self._thread.join()
        self._closed = True

    # -------------------------------------------------------------- extras
    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """A named string map stored in the file (the node's config, for replay)."""
        with self._cond:
            if not self._closing:
                self._queue.append(("meta", name, {str(k): str(v) for k, v in data.items()}))

    def flush(self, timeout_s: float = 10.0) -> bool:
        """Write everything queued so far as a chunk, now; True once it is on disk."""
        done = threading.Event()
        with self._cond:
            if self._closing:
                return False
            self._queue.append(("flush", done))
            self._cond.notify()
        return done.wait(timeout_s)

    def stats(self) -> dict[str, Any]:
        with self._cond:
            queued = len(self._queue)
        return {
            "path": str(self.path),
            "records_written": self.records_written,
            "records_dropped": self.records_dropped,
            "records_nonfinite": self.records_nonfinite,
            "records_queued": queued,
            "records_flushed": self.records_flushed,
            "chunks_flushed": self.chunks_flushed,
            "bytes": self._file.tell() if not self._file.closed else self.path.stat().st_size,
            "failed": self._failed,
        }

    def __enter__(self) -> McapRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -------------------------------------------------------- writer thread
    def _run(self) -> None:
        next_flush = time.monotonic() + self.flush_interval_s
        while True:
            with self._cond:
                while not self._queue and not self._closing:
                    timeout = next_flush - time.monotonic()
                    if timeout <= 0:
                        break
                    self._cond.wait(min(timeout, 0.2))
                items = list(self._queue)
                self._queue.clear()
                closing = self._closing
            flush_now = False
            for item in items:
                if self._failed is not None:
                    break
                try:
                    if item[0] == "msg":
                        self._add(item[1], item[2], item[3])
                    elif item[0] == "meta":
                        self._writer.add_metadata(item[1], item[2])
                    else:
                        flush_now = True
                except Exception as e:  # a bad record must not stop the recording
                    if isinstance(e, OSError):
                        self._fail(e)
                    else:
                        log.exception("recorder: cannot write a %s record", item[1])
            if self._failed is None and (flush_now or closing or time.monotonic() >= next_flush):
                self._flush_chunk()
                next_flush = time.monotonic() + self.flush_interval_s
            for item in items:
                if item[0] == "flush":
                    item[1].set()
            if closing:
                with self._cond:
                    if self._queue:
                        continue
                self._finish()
                return

    def _add(self, channel: str, t_ns: int, record: dict[str, Any]) -> None:
        if self._decode_wire and isinstance(record.get("wire"), (bytes, bytearray)):
            record["decoded"] = _decoded_fields(bytes(record["wire"]))
        t_wall_ns = t_ns + self.wall_offset_ns
        if channel in foxglove.IN_PLACE:
            record.update(foxglove.camera_fields(record, t_wall_ns))
        self._add_json(channel, t_ns, record)
        self.records_written += 1  # the records given; their Foxglove views are not counted
        if self._foxglove:
            for topic, message in foxglove.views(channel, record, t_wall_ns):
                self._add_view(topic, channel, t_ns, message)

    def _add_view(self, topic: str, source: str, t_ns: int, message: dict[str, Any]) -> None:
        """A Foxglove message derived from a record, on a channel of its own."""
        state = self._channels.get(topic)
        if state is None:
            state = self._register_typed(topic, foxglove.VIEW_TOPICS[topic], {VIEW_OF_KEY: source})
        self._write_message(state, t_ns, json.dumps(message, separators=(",", ":")).encode())

    def _add_json(self, channel: str, t_ns: int, record: dict[str, Any]) -> None:
        encs: dict[str, str] = {}
        nonfinite: list[str] = []
        body = _to_json(record, "", encs, nonfinite)
        state = self._channels.get(channel)
        if state is None:
            state = self._register(channel, body, encs)
        if encs != state.encs:
            body[ENC_KEY] = encs
        if nonfinite:
            body[NONFINITE_KEY] = nonfinite
            self.records_nonfinite += 1
        self._write_message(
            state, t_ns, json.dumps(body, separators=(",", ":"), allow_nan=False).encode()
        )

    def _write_message(self, state: _ChannelState, t_ns: int, data: bytes) -> None:
        state.seq += 1
        self._writer.add_message(
            state.id,
            log_time=max(0, t_ns + self.wall_offset_ns),
            data=data,
            publish_time=max(0, t_ns),
            sequence=state.seq & 0xFFFFFFFF,
        )

    def _register_typed(
        self, channel: str, type_name: str, metadata: dict[str, str] | None = None
    ) -> _ChannelState:
        """A channel whose schema is one of Foxglove's (docs/recording.md, "Foxglove")."""
        schema = foxglove.SCHEMAS[type_name]
        schema_id = self._writer.register_schema(
            type_name, SCHEMA_ENCODING, json.dumps(schema).encode()
        )
        cid = self._writer.register_channel(channel, MESSAGE_ENCODING, schema_id, metadata or {})
        state = _ChannelState(cid, _encodings_in_schema(schema))
        self._channels[channel] = state
        return state

    def _register(self, channel: str, body: dict[str, Any], encs: dict[str, str]) -> _ChannelState:
        if channel in foxglove.IN_PLACE:
            return self._register_typed(channel, foxglove.IN_PLACE[channel])
        if channel == foxglove.LOG_CHANNEL:
            return self._register_typed(channel, "foxglove.Log")
        schema = _schema_of(body, "", encs) or {"type": "object", "properties": {}}
        schema["title"] = channel
        if channel in CHANNELS:
            schema["description"] = CHANNELS[channel]
        schema_id = self._writer.register_schema(
            SCHEMA_PREFIX + channel, SCHEMA_ENCODING, json.dumps(schema).encode()
        )
        cid = self._writer.register_channel(channel, MESSAGE_ENCODING, schema_id)
        state = _ChannelState(cid, _encodings_in_schema(schema))
        self._channels[channel] = state
        return state

    def _flush_chunk(self) -> None:
        try:
            self._writer.flush()
            if self._fsync:
                os.fsync(self._file.fileno())
        except OSError as e:
            self._fail(e)
            return
        self.chunks_flushed += 1
        self.records_flushed = self.records_written
        self.last_flush_ns = time.monotonic_ns()

    def _finish(self) -> None:
        try:
            if self._failed is None:
                self._writer.finish()
                self._file.flush()
                if self._fsync:
                    os.fsync(self._file.fileno())
        except OSError as e:
            self._fail(e)
        finally:
            with contextlib.suppress(OSError):
                self._file.close()
        log.info(
            "recording %s closed: %d records, %d dropped",
            self.path,
            self.records_written,
            self.records_dropped,
        )

    def _fail(self, e: OSError) -> None:
        self._failed = f"{type(e).__name__}: {e}"
        log.error("recording %s stopped: %s; the nodes keep running", self.path, e)


class _LogHandler(logging.Handler):
    """The process's log lines into the recording, as ``foxglove.Log`` on the ``log`` channel.

    ``emit`` only queues (``McapRecorder.write``); lines logged by the recorder's
    own writer thread, or while this handler is already writing one (a full
    queue logs), are left out so a line can never feed itself.
    """

    def __init__(self, recorder: McapRecorder, level: int) -> None:
        super().__init__(level)
        self.recorder = recorder
        self._inside = threading.local()

    def emit(self, record: logging.LogRecord) -> None:
        if threading.current_thread() is self.recorder._thread or getattr(
            self._inside, "on", False
        ):
            return
        self._inside.on = True
        try:
            message = foxglove.log_message(record, record.getMessage())
            self.recorder.write(foxglove.LOG_CHANNEL, time.monotonic_ns(), message)
        except Exception:  # a line that cannot be formatted must not break the caller
            self.handleError(record)
        finally:
            self._inside.on = False


# -------------------------------------------------------------------- reader
MAGIC = b"\x89MCAP0\r\n"
_CHUNK_OPCODE = 0x06
_FOOTER_OPCODE = 0x02
_FOOTER_LEN = 20  # summary_start, summary_offset_start (8 each), summary_crc (4)
_SCAN_BLOCK = 1 << 20


@dataclasses.dataclass
class Damage:
    """A stretch of a recording that could not be read, and what it cost.

    ``records_lost`` counts, per channel, the records missing from the
    channel's sequence numbers across the stretch (the recorder numbers each
    channel's records from 1), so a lost chunk's frames are counted exactly
    once reading has resumed.
    """

    byte_start: int
    byte_end: int  # where reading resumed
    error: str
    t_before_ns: int | None  # publish time of the newest record read before the stretch
    t_after_ns: int | None = None  # of the first record read after it
    records_lost: dict[str, int] = dataclasses.field(default_factory=dict)


class RecordingReader:
    """Reads a recording front to back, also one cut short by a crash or damaged inside.

    Only the data section is read (chunks, in file order), never the summary,
    so a file without a footer reads the same as a closed one. A chunk that
    fails its CRC or does not parse is skipped: reading goes on at the next
    chunk that checks out (found by scanning for one), and ``damage`` lists
    each skipped stretch with the time range and the records it lost. Where
    no whole chunk follows, the file was cut short: ``truncated`` says so and
    ``bytes_unread`` how much was left. ``complete``: the file was closed
    cleanly (its footer is there), whatever lies between.
    """

    def __init__(self, path: str | os.PathLike[str], *, views: bool = False) -> None:
        self.path = Path(path)
        self.views = views  # also the Foxglove views derived from records (docs/recording.md)
        if not self.path.exists():
            raise RecordingError(f"no recording at {self.path}")
        self.metadata: dict[str, dict[str, str]] = {}
        self.truncated = False
        self.complete = False  # the footer is there: the file was closed cleanly
        self.bytes_unread = 0
        self.error: str | None = None
        self.damage: list[Damage] = []

    def __iter__(self) -> Iterator[tuple[str, int, dict[str, Any]]]:
        schemas: dict[int, dict[str, Any]] = {}
        channels: dict[int, tuple[str, dict[str, str]] | None] = {}  # None: a view, skipped
        #: per channel: the newest sequence number read, how many damages came before it,
        #: how many records were read
        seen: dict[str, tuple[int, int, int]] = {}
        summary = None
        size = self.path.stat().st_size
        last_t: int | None = None
        with open(self.path, "rb") as f:
            head = f.read(len(MAGIC))
            if len(head) < len(MAGIC) and MAGIC.startswith(head):  # cut before its first record
                self.truncated = True
                self.error = f"the file ends after {len(head)} bytes, inside MCAP's magic"
                return
            if head != MAGIC:
                raise RecordingError(
                    f"{self.path} is not an MCAP file (it does not start with MCAP's magic "
                    "bytes): is it a recording?"
                )
            f.seek(0)
            reader = StreamReader(f, emit_chunks=True, record_size_limit=256 << 20)
            good_end = len(MAGIC)
            while True:
                try:
                    for rec in reader.records:
                        if isinstance(rec, Chunk):
                            inner = breakup_chunk(rec, validate_crc=True)
                        else:
                            inner = [rec]
                        for r in inner:
                            if isinstance(r, Schema):
                                schemas[r.id] = _parse_schema(r)
                            elif isinstance(r, Channel):
                                channels[r.id] = self._channel(r, schemas)
                            elif isinstance(r, Message):
                                out = self._message(r, channels)
                                if out is not None:
                                    self._count_lost(out[0], r.sequence, out[1], seen)
                                    last_t = out[1]
                                    yield out
                            elif isinstance(r, Metadata):
                                self.metadata[r.name] = dict(r.metadata)
                        good_end = f.tell()
                        if isinstance(rec, Footer):
                            self.complete = True
                    if self.damage:
                        self._settle(summary, seen)
                    return
                except Exception as e:  # damaged data raises many types (mcap, struct, zstd)
                    error = f"{type(e).__name__}: {e}"
                if not self.damage:  # a lost chunk may have held channels the rest uses
                    summary = _channels_from_summary(f, schemas, channels, self._channel)
                resume = _next_chunk(f, good_end + 1, size)
                if resume is None:
                    self._ended_early(f, size, good_end, error, last_t)
                    if self.complete:
                        self._settle(summary, seen)
                    return
                log.warning(
                    "%s: bytes %d..%d unreadable (%s); reading goes on at the next chunk",
                    self.path,
                    good_end,
                    resume,
                    error,
                )
                self.damage.append(Damage(good_end, resume, error, last_t))
                f.seek(resume)
                reader = StreamReader(
                    f, skip_magic=True, emit_chunks=True, record_size_limit=256 << 20
                )
                good_end = resume

    def _count_lost(
        self, topic: str, sequence: int, t_ns: int, seen: dict[str, tuple[int, int, int]]
    ) -> None:
        """Charge a gap in a channel's sequence numbers to the damage read since its last record.

        The recorder numbers only the records it wrote (a dropped one gets no
        number), so a gap is always a loss in the file.
        """
        if self.damage and self.damage[-1].t_after_ns is None:
            self.damage[-1].t_after_ns = t_ns
        last_seq, damages_before, count = seen.get(topic, (0, 0, 0))
        seen[topic] = (sequence, len(self.damage), count + 1)
        lost = (sequence - last_seq - 1) & 0xFFFFFFFF
        if lost and damages_before < len(self.damage):
            counts = self.damage[-1].records_lost
            counts[topic] = counts.get(topic, 0) + lost

    def _settle(self, summary: Any, seen: dict[str, tuple[int, int, int]]) -> None:
        """Records lost after a channel's last readable one: the summary's counts say how many."""
        stats = getattr(summary, "statistics", None)
        if stats is None:
            return
        for cid, expected in stats.channel_message_counts.items():
            channel = summary.channels.get(cid)
            if channel is None or (VIEW_OF_KEY in (channel.metadata or {}) and not self.views):
                continue
            topic = channel.topic
            accounted = sum(d.records_lost.get(topic, 0) for d in self.damage)
            missing = expected - seen.get(topic, (0, 0, 0))[2] - accounted
            if missing > 0:
                counts = self.damage[-1].records_lost
                counts[topic] = counts.get(topic, 0) + missing

    def _ended_early(
        self, f: BinaryIO, size: int, good_end: int, error: str, last_t: int | None
    ) -> None:
        """No whole chunk after ``good_end``: a cut file, or a closed one damaged at its end."""
        if _has_footer(f, size):
            self.complete = True
            self.damage.append(Damage(good_end, size, error, last_t))
            log.warning("%s: bytes %d..%d unreadable (%s)", self.path, good_end, size, error)
            return
        self.truncated = True
        self.error = error
        self.bytes_unread = max(0, size - good_end)
        log.info("%s ends early (%s); read up to byte %d", self.path, error, good_end)

    def _channel(
        self, ch: Channel, schemas: dict[int, dict[str, Any]]
    ) -> tuple[str, dict[str, str]] | None:
        """(topic, encodings) of a channel to read; None for a Foxglove view when not asked."""
        if VIEW_OF_KEY in (ch.metadata or {}) and not self.views:
            return None
        return ch.topic, _encodings_in_schema(schemas.get(ch.schema_id, {}))

    def _message(
        self, msg: Message, channels: dict[int, tuple[str, dict[str, str]] | None]
    ) -> tuple[str, int, dict[str, Any]] | None:
        found = channels.get(msg.channel_id)
        if found is None:
            return None
        topic, encs = found
        try:
            record = json.loads(msg.data)
        except ValueError:
            return None
        if not isinstance(record, dict):
            return None
        own = record.pop(ENC_KEY, None)
        _restore(record, own if isinstance(own, dict) else encs)
        return topic, msg.publish_time, record


def _channels_from_summary(
    f: BinaryIO,
    schemas: dict[int, dict[str, Any]],
    channels: dict[int, tuple[str, dict[str, str]] | None],
    channel_of: Any,
) -> Any:
    """Add the channels a closed file's summary lists (a clean close repeats them all there).

    Returns the summary (its statistics count every channel's records), or None.
    """
    from mcap.reader import SeekingReader

    try:
        f.seek(0)
        summary = SeekingReader(f).get_summary()
    except Exception:  # no footer (a killed node) or a damaged summary: nothing to add
        return None
    if summary is None:
        return None
    for sid, schema in summary.schemas.items():
        schemas.setdefault(sid, _parse_schema(schema))
    for cid, ch in summary.channels.items():
        if cid not in channels:
            channels[cid] = channel_of(ch, schemas)
    return summary


def _next_chunk(f: BinaryIO, start: int, size: int) -> int | None:
    """The offset of the first chunk at or after ``start`` that parses and passes its CRC."""
    pos = start
    while pos < size:
        f.seek(pos)
        block = f.read(_SCAN_BLOCK + 64)
        i = block.find(bytes([_CHUNK_OPCODE]))
        while 0 <= i < min(len(block), _SCAN_BLOCK):
            if _is_chunk(f, pos + i, size):
                return pos + i
            i = block.find(bytes([_CHUNK_OPCODE]), i + 1)
        pos += _SCAN_BLOCK
    return None


def _is_chunk(f: BinaryIO, at: int, size: int) -> bool:
    f.seek(at)
    head = f.read(1 + 8 + 8 + 8 + 8 + 4 + 4)
    if len(head) < 41:
        return False
    length = int.from_bytes(head[1:9], "little")
    comp_len = int.from_bytes(head[37:41], "little")
    if at + 9 + length > size or comp_len > 16 or length < 40 + comp_len:
        return False
    f.seek(at)
    try:
        rec = next(
            iter(
                StreamReader(
                    f, skip_magic=True, emit_chunks=True, record_size_limit=length + 1
                ).records
            )
        )
        if not isinstance(rec, Chunk):
            return False
        breakup_chunk(rec, validate_crc=True)
    except Exception:  # any failure: not a chunk
        return False
    return True


def _has_footer(f: BinaryIO, size: int) -> bool:
    """The file ends with a footer record and the magic: it was closed cleanly."""
    tail = 1 + 8 + _FOOTER_LEN + len(MAGIC)
    if size < len(MAGIC) + tail:
        return False
    f.seek(size - tail)
    data = f.read(tail)
    return (
        data[0] == _FOOTER_OPCODE
        and int.from_bytes(data[1:9], "little") == _FOOTER_LEN
        and data[-len(MAGIC) :] == MAGIC
    )


def _parse_schema(schema: Schema) -> dict[str, Any]:
    if schema.encoding != SCHEMA_ENCODING:
        return {}
    try:
        out = json.loads(schema.data)
    except ValueError:
        return {}
    return out if isinstance(out, dict) else {}


def read_recording(
    path: str | os.PathLike[str], *, views: bool = False
) -> Iterator[tuple[str, int, dict[str, Any]]]:
    """(channel, t_ns, record) in file order; stops quietly where a crash cut the file.

    ``views``: also the Foxglove messages the recorder derived from the records
    (pads, transforms, the palm's scene); off, old and new files read alike.
    """
    yield from RecordingReader(path, views=views)


def read_metadata(path: str | os.PathLike[str]) -> dict[str, dict[str, str]]:
    """The metadata records (clock offset, the node's config) of a recording."""
    reader = RecordingReader(path)
    for _ in reader:
        pass
    return reader.metadata


def node_recorder(path: str | os.PathLike[str], config: Any, node: str) -> McapRecorder:
    """A recorder for a node, with its effective config stored for ``deepxpalm replay``."""
    from common.config import config_toml

    return McapRecorder(
        path,
        metadata={"deepxpalm.node": {"node": node, "config_toml": config_toml(config, node)}},
        log_level=logging.INFO,
    )


def recover_recording(src: str | os.PathLike[str], dst: str | os.PathLike[str]) -> int:
    """Copy every whole chunk of ``src`` (a killed node's file) into ``dst``, with an index.

    Foxglove opens a file without a summary only as "unindexed" (it reads it
    all); the copy has the summary and footer a clean close writes. Records
    are copied as they are, times and bytes unchanged. Returns the message count.
    """
    out = open(dst, "wb")  # noqa: SIM115 (the writer's finish() needs it open)
    writer = Writer(out, compression=CompressionType.ZSTD)
    writer.start(profile="", library=LIBRARY + " (recovered)")
    schema_ids: dict[int, int] = {}
    channel_ids: dict[int, int] = {}
    count = 0
    try:
        with open(src, "rb") as f:
            try:
                for rec in StreamReader(f, emit_chunks=True, record_size_limit=256 << 20).records:
                    inner = (
                        breakup_chunk(rec, validate_crc=True) if isinstance(rec, Chunk) else [rec]
                    )
                    for r in inner:
                        if isinstance(r, Schema) and r.id not in schema_ids:
                            schema_ids[r.id] = writer.register_schema(r.name, r.encoding, r.data)
                        elif isinstance(r, Channel) and r.id not in channel_ids:
                            channel_ids[r.id] = writer.register_channel(
                                r.topic,
                                r.message_encoding,
                                schema_ids.get(r.schema_id, 0),
                                r.metadata,
                            )
                        elif isinstance(r, Message) and r.channel_id in channel_ids:
                            writer.add_message(
                                channel_ids[r.channel_id],
                                r.log_time,
                                r.data,
                                r.publish_time,
                                r.sequence,
                            )
                            count += 1
                        elif isinstance(r, Metadata):
                            writer.add_metadata(r.name, dict(r.metadata))
                    if isinstance(rec, Footer):
                        break
            except Exception as e:  # the cut: everything before it is copied
                log.info("%s ends early (%s); recovered %d messages", src, e, count)
        writer.finish()
    finally:
        out.close()
    return count
