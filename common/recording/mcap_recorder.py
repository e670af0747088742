"""Recording to MCAP, the log format Foxglove opens, in a form that survives ``kill -9``.

Format (docs/recording.md; ``common.recording.mcap_json`` and ``common.recording.mcap_channels``
write it, ``common.recording.mcap_reader`` reads it): one MCAP channel per
``common.recording.channels.CHANNELS`` name, messages JSON with an inferred JSON Schema,
because Foxglove plots JSON channels without any plugin. NumPy arrays become nested lists and bytes
become base64 strings; the schema marks them (``x-numpy-dtype``,
``contentEncoding: base64``) so ``read_recording`` gives back the same
arrays and bytes. A record holding the wire bytes of a message (``wire``)
also gets its decoded fields (``decoded``), so a stimulus can be plotted.

Foxglove (``common/recording/foxglove.py``): the camera's pictures and the log lines
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

import collections
import contextlib
import logging
import os
import threading
import time
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from mcap.writer import Writer

from common.clocks.clock import wall_offset_ns
from common.logs import BurstLog
from common.recording import foxglove
from common.recording.mcap_channels import McapChannels
from common.recording.mcap_json import (
    COMPRESSION,
    LIBRARY,
    RecordingError,
)

# the reader's names, where the recording's users have always found them
from common.recording.mcap_reader import (
    Damage,
    RecordingReader,
    read_metadata,
    read_recording,
    recover_recording,
)

__all__ = [
    "Damage",
    "McapRecorder",
    "RecordingError",
    "RecordingReader",
    "node_recorder",
    "read_metadata",
    "read_recording",
    "recover_recording",
]

log = logging.getLogger(__name__)


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
        if compression not in COMPRESSION:
            raise ValueError(f"compression must be one of {sorted(COMPRESSION)}")
        self.path = Path(path)
        self.flush_interval_s = float(flush_interval_s)
        self.max_queue = int(max_queue)
        self._fsync = fsync
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file: BinaryIO = open(self.path, "wb")  # noqa: SIM115 (closed by the writer thread)
        except OSError as e:
            raise RecordingError(f"cannot open {self.path} for recording: {e}") from None
        self._writer = Writer(
            self._file, chunk_size=chunk_size, compression=COMPRESSION[compression]
        )
        self._writer.start(profile="", library=LIBRARY)
        self.wall_offset_ns = wall_offset_ns()
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
        self._channels = McapChannels(
            self._writer,
            self.wall_offset_ns,
            decode_wire=decode_wire,
            foxglove_views=foxglove_views,
        )
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
        if self._channels.add_record(channel, t_ns, record):
            self.records_nonfinite += 1
        self.records_written += 1  # the records given; their Foxglove views are not counted
        self._channels.add_views(channel, t_ns, record)

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


def node_recorder(path: str | os.PathLike[str], config: Any, node: str) -> McapRecorder:
    """A recorder for a node, with its effective config stored for ``deepxpalm replay``."""
    from common.config.typed import config_toml

    return McapRecorder(
        path,
        metadata={"deepxpalm.node": {"node": node, "config_toml": config_toml(config, node)}},
        log_level=logging.INFO,
    )
