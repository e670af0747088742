"""The tactile board's serial frame format: encoder, decoder, streaming parser.

docs/tactile-wire.md is the byte-by-byte description a firmware engineer
implements; this module is its reference implementation, used by both the
driver (decode) and the board simulator (encode), so the two cannot drift.

One packet carries one pad of one scan. Both pads of a scan share a
sequence number, so the driver can pair them and see gaps.

    offset size  field
    0      2     sync            0xA5 0x5A
    2      1     version         0x01
    3      1     pad             0 = finger 1, 1 = finger 2
    4      4     seq             uint32 LE, +1 per scan, wraps
    8      1     rows            10
    9      1     cols            10
    10     200   counts          100 x uint16 LE, row-major, the pad's own view
    210    2     crc             CRC-16/CCITT-FALSE of bytes 2..209, LE

The parser is built for a lossy line: on any doubt (a header that is not
this format, a CRC that fails) it drops ONE byte and searches for the next
sync again, so a packet that starts inside a truncated one is still found.
"""

from __future__ import annotations

import binascii
import struct
from dataclasses import dataclass, field

import numpy as np

SYNC = b"\xa5\x5a"
VERSION = 1
N_PADS = 2
ROWS = 10
COLS = 10
N_TAXELS = ROWS * COLS
HEADER = struct.Struct("<2sBBIBB")  # sync, version, pad, seq, rows, cols
HEADER_SIZE = HEADER.size  # 10
PAYLOAD_SIZE = 2 * N_TAXELS  # 200
CRC_SIZE = 2
PACKET_SIZE = HEADER_SIZE + PAYLOAD_SIZE + CRC_SIZE  # 212
SEQ_MODULO = 1 << 32
COUNTS_DTYPE = np.dtype("<u2")
_CRC = struct.Struct("<H")

#: the default line rate: 240 packets/s x 212 bytes = 50.9 kB/s, 55 % of 921600 8N1
DEFAULT_BAUD = 921_600


def crc16_ccitt(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, no final xor.

    ``binascii.crc_hqx`` is exactly this CRC when seeded with 0xFFFF and runs
    in C (about 0.3 us for a packet); check value: b"123456789" -> 0x29B1.
    """
    return binascii.crc_hqx(data, 0xFFFF)


@dataclass(frozen=True, slots=True)
class PadPacket:
    pad: int  # 0 = finger 1, 1 = finger 2
    seq: int  # uint32, shared by both pads of one scan
    payload: bytes  # the 200 count bytes as sent: 100 x uint16 LE, row-major

    @property
    def counts(self) -> np.ndarray:
        """(10, 10) uint16, the pad's own view (finger 2 NOT mirrored)."""
        return counts_of(self.payload).reshape(ROWS, COLS)


def counts_of(payload: bytes) -> np.ndarray:
    """Count bytes (one pad's payload, or several back to back) -> flat native uint16."""
    return np.frombuffer(payload, COUNTS_DTYPE).astype(np.uint16, copy=False)


def encode(pad: int, seq: int, counts: np.ndarray) -> bytes:
    """One packet for one pad. ``counts`` must be (10, 10) and fit in uint16."""
    arr = np.asarray(counts)
    if arr.shape != (ROWS, COLS):
        raise ValueError(f"counts must have shape ({ROWS}, {COLS}), not {arr.shape}")
    if not 0 <= pad < N_PADS:
        raise ValueError(f"pad must be 0 or 1, not {pad}")
    if arr.size and (arr.min() < 0 or arr.max() > 0xFFFF):
        raise ValueError("counts must lie in 0..65535 (uint16)")
    body = HEADER.pack(SYNC, VERSION, pad, seq % SEQ_MODULO, ROWS, COLS)
    body += arr.astype(COUNTS_DTYPE).tobytes()
    return body + struct.pack("<H", crc16_ccitt(body[2:]))


def decode(packet: bytes | bytearray | memoryview) -> PadPacket:
    """Decode exactly one packet; ``ValueError`` says what is wrong with it."""
    if len(packet) != PACKET_SIZE:
        raise ValueError(f"a packet is {PACKET_SIZE} bytes, not {len(packet)}")
    problem = _header_problem(packet, 0)
    if problem:
        raise ValueError(problem)
    (crc,) = struct.unpack_from("<H", packet, PACKET_SIZE - CRC_SIZE)
    calc = crc16_ccitt(memoryview(packet)[2 : PACKET_SIZE - CRC_SIZE])
    if crc != calc:
        raise ValueError(f"bad CRC: packet says 0x{crc:04x}, bytes give 0x{calc:04x}")
    return _unpack(packet, 0)


def _header_problem(buf: bytes | bytearray | memoryview, i: int) -> str | None:
    sync, version, pad, _seq, rows, cols = HEADER.unpack_from(buf, i)
    if sync != SYNC:
        return "no sync bytes"
    if version != VERSION:
        return f"unknown version {version}"
    if pad >= N_PADS:
        return f"pad id {pad} is not 0 or 1"
    if rows != ROWS or cols != COLS:
        return f"pad size {rows}x{cols} is not {ROWS}x{COLS}"
    return None


def _unpack(buf: bytes | bytearray | memoryview, i: int) -> PadPacket:
    _sync, _version, pad, seq, _rows, _cols = HEADER.unpack_from(buf, i)
    return PadPacket(pad, seq, bytes(buf[i + HEADER_SIZE : i + HEADER_SIZE + PAYLOAD_SIZE]))


@dataclass
class ParserStats:
    """What the parser saw; a healthy line has only ``packets`` and ``bytes_in`` growing."""

    bytes_in: int = 0
    packets: int = 0  # packets with a good header and CRC
    dropped_bytes: int = 0  # bytes discarded while looking for a good packet
    bad_crc: int = 0  # a plausible header whose CRC failed
    bad_header: int = 0  # sync bytes followed by a header that is not this format
    resyncs: int = 0  # times the parser had to skip bytes to find the next packet
    extra: dict[str, int] = field(default_factory=dict)

    def as_dict(self) -> dict[str, int]:
        d = {
            "bytes_in": self.bytes_in,
            "packets": self.packets,
            "dropped_bytes": self.dropped_bytes,
            "bad_crc": self.bad_crc,
            "bad_header": self.bad_header,
            "resyncs": self.resyncs,
        }
        d.update(self.extra)
        return d


class StreamParser:
    """Turns arbitrary chunks of a byte stream into good packets, in order.

    Holds at most one packet's worth of unconsumed bytes between calls, so
    memory is bounded whatever arrives. Not thread-safe: one reader owns it.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self.stats = ParserStats()
        self._skipping = False  # inside a run of discarded bytes (one resync per run)

    def feed(self, data: bytes | bytearray | memoryview) -> list[PadPacket]:
        """Append ``data`` and return every complete good packet now available.

        This runs for every scan on a core that has gone cold since the last
        one, so a good packet costs one header unpack, one CRC over a view (no
        copy) and one copy of its payload; the checks that name a problem run
        only when the quick one fails.
        """
        self.stats.bytes_in += len(data)
        buf = self._buf
        buf += data
        out: list[PadPacket] = []
        i = 0
        n = len(buf)
        with memoryview(buf) as view:  # released before buf is resized below
            while True:
                j = buf.find(SYNC, i)
                if j < 0:
                    # Keep a trailing 0xA5: it may be the first half of the next sync.
                    keep_from = n - 1 if n and buf[-1] == SYNC[0] else n
                    keep_from = max(keep_from, i)
                    self._drop(keep_from - i)
                    i = keep_from
                    break
                self._drop(j - i)
                i = j
                if n - i < HEADER_SIZE:
                    break
                _sync, version, pad, seq, rows, cols = HEADER.unpack_from(buf, i)
                if version != VERSION or pad >= N_PADS or rows != ROWS or cols != COLS:
                    self.stats.bad_header += 1
                    self._drop(1)
                    i += 1
                    continue
                if n - i < PACKET_SIZE:
                    break
                end = i + PACKET_SIZE
                if _CRC.unpack_from(buf, end - CRC_SIZE)[0] != crc16_ccitt(
                    view[i + 2 : end - CRC_SIZE]
                ):
                    self.stats.bad_crc += 1
                    self._drop(1)
                    i += 1
                    continue
                out.append(PadPacket(pad, seq, bytes(view[i + HEADER_SIZE : end - CRC_SIZE])))
                self.stats.packets += 1
                self._skipping = False
                i = end
        del buf[:i]
        return out

    def _drop(self, n: int) -> None:
        if n <= 0:
            return
        self.stats.dropped_bytes += n
        if not self._skipping:
            self.stats.resyncs += 1
            self._skipping = True

    def reset(self) -> None:
        """Forget buffered bytes (after a reconnect the old tail means nothing)."""
        self._buf.clear()
        self._skipping = False
