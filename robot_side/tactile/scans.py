"""The board's packets into scans: the two pads of one scan paired, each scan numbered.

Each pad's packet carries the board's wrapping uint32 sequence number; a scan
is complete when both pads of one number have arrived. Scans are numbered on
a count that only grows, with gaps kept visible and a board restart (the
number steps back) never taking the count back.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from robot_side.tactile.board_calibration import WIRE_SHAPE
from robot_side.tactile.wire import SEQ_MODULO, PadPacket

log = logging.getLogger(__name__)


class ScanPairing:
    """Pairs pads into scans and numbers them; ``on_scan(seq, wire_seq, payloads, t_ns)``
    gets each new scan (both pads' count bytes, pad 0 first).

    Counts into ``counters``: ``incomplete_frames``, ``seq_gaps``,
    ``duplicate_frames``, ``board_restarts``.
    """

    def __init__(
        self, counters: dict[str, int], on_scan: Callable[[int, int, bytes, int], None]
    ) -> None:
        self._counters = counters
        self._on_scan = on_scan
        self._pending_seq: int | None = None
        self._pending: dict[int, bytes] = {}
        self._last_wire_seq: int | None = None
        #: the newest scan's number (0 before the first)
        self.published_seq = 0

    def reset(self) -> None:
        """A new stream (connect, a reopened port): a half-paired scan is dropped."""
        self._pending_seq = None
        self._pending = {}

    def accept(self, packet: PadPacket, t_ns: int) -> None:
        """One pad's packet; a complete scan goes to ``on_scan`` unless it repeats the last."""
        if packet.seq != self._pending_seq:
            if self._pending:
                self._counters["incomplete_frames"] += 1
            self._pending = {}
            self._pending_seq = packet.seq
        pending = self._pending
        pending[packet.pad] = packet.payload
        if len(pending) == WIRE_SHAPE[0]:
            self._pending = {}
            self._pending_seq = None
            seq = self._next_seq(packet.seq)
            if seq is not None:
                self._on_scan(seq, packet.seq, pending[0] + pending[1], t_ns)

    def _next_seq(self, wire_seq: int) -> int | None:
        """Map the board's wrapping uint32 onto a count that only grows.

        The first frame ever seen gets the board's number + 1 (so a scan's
        wire number is ``seq - 1`` until the board restarts, which keeps logs
        comparable with the board's). A forward jump keeps its size (gaps
        stay visible as drops); a step back means the board restarted (power
        cycle, replug), which must not make the published sequence go back.
        """
        last = self._last_wire_seq
        self._last_wire_seq = wire_seq
        if last is None:
            self.published_seq = wire_seq + 1
            return self.published_seq
        d = (wire_seq - last) % SEQ_MODULO
        if d == 0:
            self._counters["duplicate_frames"] += 1
            return None
        if d < SEQ_MODULO // 2:
            step = d
            self._counters["seq_gaps"] += d - 1
        else:
            step = 1
            self._counters["board_restarts"] += 1
            log.warning("tactile board sequence went back (%d -> %d): restarted?", last, wire_seq)
        self.published_seq += step
        return self.published_seq
