"""A live view in Foxglove: the recordings being written, served by Foxglove's WebSocket server.

The robot PC's processes each record their own file (the robot node
``robot.mcap``, the video server ``camera.mcap``; docs/recording.md), and
only together do they hold the camera, the pads, the arm and the palm. So
the live source is an observer of those files, not a part of any node:
``FileFollower`` reads each ``*.mcap`` of a session folder as it grows (a
recorder writes a whole chunk every second), and ``LiveSource`` hands every
message to the live view's server (``common/live_view/server.py``: Foxglove's
WebSocket server, the ``foxglove`` extra; ``deepxpalm view`` and ``deepxpalm
record`` share it) on the same channel, schema and bytes as in the file: the
Foxglove types, the nodes' own channels and the log lines alike.

Pacing: a message is sent ``delay_s`` after its recorded time (the
recording's monotonic clock, the same PC's), so the camera's 10 pictures a
second arrive 100 ms apart, not as a burst each time a chunk lands. What
was due before the view started (the files' history) is skipped, so the
view shows now, not a replay; a message read after its time (a loaded
machine, a stalled disk) is sent at once and counted as late.

Nothing here touches a node: a slow or stopped Foxglove client costs the
robot nothing (the server drops the oldest messages for a slow client).
"""

from __future__ import annotations

import heapq
import io
import itertools
import logging
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

from mcap.records import Channel, DataEnd, Footer, Message, Schema
from mcap.stream_reader import StreamReader

from common.errors import ConfigError
from common.live_view.server import LiveServer
from common.recording.foxglove import FoxgloveLiveConfig

log = logging.getLogger(__name__)

_MAGIC = b"\x89MCAP0\r\n"
_HEAD = 9  # opcode (1) and length (8) of every MCAP record


class _Tail:
    """One recording being written: the whole records appended since the last read."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.pos = 0
        self.done = False  # its footer was read: the recorder closed it

    def read(self) -> list[Any]:
        try:
            with open(self.path, "rb") as f:
                f.seek(self.pos)
                data = f.read()
        except OSError:
            return []
        out: list[Any] = []
        i = 0
        if self.pos == 0:
            if len(data) < len(_MAGIC):
                return []
            if data[: len(_MAGIC)] != _MAGIC:
                log.warning("%s is not an MCAP file; not followed", self.path)
                self.done = True
                return []
            i = len(_MAGIC)
        while len(data) - i >= _HEAD:
            length = int.from_bytes(data[i + 1 : i + _HEAD], "little")
            end = i + _HEAD + length
            if end > len(data):
                break  # the rest of this record is not written yet
            try:
                reader = StreamReader(io.BytesIO(data[i:end]), skip_magic=True)
                out.extend(reader.records)
            except Exception as e:  # a damaged chunk: skip it, as the reader does
                log.debug("%s: a record at %d does not parse (%s)", self.path, self.pos + i, e)
            i = end
        self.pos += i
        if any(isinstance(r, (Footer, DataEnd)) for r in out):
            self.done = True
        return out


class FileFollower:
    """Every ``*.mcap`` in a folder, read as it grows: (file, record) in file order."""

    def __init__(self, folder: Path) -> None:
        self.folder = Path(folder)
        self._tails: dict[Path, _Tail] = {}

    def poll(self) -> list[tuple[Path, Any]]:
        for path in sorted(self.folder.glob("*.mcap")):
            if path not in self._tails:
                self._tails[path] = _Tail(path)
        out = []
        for path, tail in self._tails.items():
            if not tail.done:
                out.extend((path, r) for r in tail.read())
        return out


class LiveSource:
    """A session's recordings, fed to the live view's Foxglove server (``LiveServer``).

    ``server``: a server another source shares (``deepxpalm view``, with the
    robot's link beside the files), left open by ``close``; unset, the source
    starts and stops its own. ``skip_topics``: topics another source serves (the
    link's, which are newer than the files'), not served from the files.
    """

    def __init__(
        self,
        config: FoxgloveLiveConfig,
        server: LiveServer | None = None,
        skip_topics: frozenset[str] = frozenset(),
    ) -> None:
        if config.follow is None:
            raise ConfigError("foxglove.follow: which session folder to serve (e.g. runs/today)")
        self.config = config
        self._follower = FileFollower(config.follow)
        self._schemas: dict[tuple[Path, int], Schema] = {}
        self._channels: dict[tuple[Path, int], Any] = {}  # (file, channel id) -> sdk channel
        self._skip = skip_topics
        self._due: list[tuple[int, int, Any, bytes, int]] = []
        self._order = itertools.count()
        self.counters: Counter[str] = Counter()
        self._t_start = time.monotonic_ns()
        self._own_server = server is None
        self.server = LiveServer(config) if server is None else server
        self.port = self.server.port
        log.info(
            "Foxglove: open %s (Open connection, Foxglove WebSocket); following %s",
            self.server.url,
            config.follow,
        )

    def _channel(self, path: Path, ch: Channel) -> Any:
        if ch.topic in self._skip:
            return None
        schema = self._schemas.get((path, ch.schema_id))
        if schema is None:
            return self.server.channel(ch.topic, message_encoding=ch.message_encoding)
        return self.server.channel(
            ch.topic,
            schema_name=schema.name,
            schema_encoding=schema.encoding,
            schema_data=schema.data,
            message_encoding=ch.message_encoding,
        )

    def step(self) -> None:
        """Read what the files gained and send what is due."""
        now = time.monotonic_ns()
        delay_ns = round(self.config.delay_s * 1e9)
        for path, rec in self._follower.poll():
            if isinstance(rec, Schema):
                self._schemas[(path, rec.id)] = rec
            elif isinstance(rec, Channel):
                self._channels[(path, rec.id)] = self._channel(path, rec)
            elif isinstance(rec, Message):
                channel = self._channels.get((path, rec.channel_id))
                if channel is None:
                    continue
                due = rec.publish_time + delay_ns
                if due < self._t_start:  # the file's history: the view shows from now on
                    self.counters["skipped_history"] += 1
                    continue
                if due < now:  # read late (a loaded machine, a stalled disk): sent at once
                    self.counters["late"] += 1
                heapq.heappush(self._due, (due, next(self._order), channel, rec.data, rec.log_time))
        while self._due and self._due[0][0] <= now:
            _, _, channel, data, log_time = heapq.heappop(self._due)
            channel.log(data, log_time=log_time)
            self.counters["sent"] += 1

    def wait_s(self) -> float:
        """How long until ``step`` has something to do: the next message due, or the next look
        at the files."""
        wait = self.config.poll_interval_s
        if self._due:
            wait = min(wait, max(0.0, (self._due[0][0] - time.monotonic_ns()) / 1e9))
        return wait

    def run(self, stop: threading.Event, duration_s: float | None = None) -> None:
        t_end = None if duration_s is None else time.monotonic() + duration_s
        try:
            while not stop.is_set() and (t_end is None or time.monotonic() < t_end):
                self.step()
                stop.wait(self.wait_s())
        finally:
            self.close()

    def close(self) -> None:
        """Stops the server if this source started it (a shared one is its owner's to stop)."""
        if self._own_server:
            self.server.close()
