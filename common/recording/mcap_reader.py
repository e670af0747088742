"""Reading a recording front to back, also one cut short by a crash or damaged inside.

Only the data section is read (chunks, in file order), never the summary, so
a file without a footer (a killed node's) reads the same as a closed one. A
chunk that fails its CRC or does not parse is skipped and counted
(``Damage``); ``recover_recording`` copies a killed node's file into one with
the index a clean close writes. Format: docs/recording.md.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any, BinaryIO

from mcap.records import Channel, Chunk, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType, Writer

from common.recording.mcap_json import (
    ENC_KEY,
    LIBRARY,
    SCHEMA_ENCODING,
    VIEW_OF_KEY,
    RecordingError,
    encodings_in_schema,
    restore,
)

log = logging.getLogger(__name__)

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
        return ch.topic, encodings_in_schema(schemas.get(ch.schema_id, {}))

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
        restore(record, own if isinstance(own, dict) else encs)
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
