"""The 60 Hz goal write as bytes: one STS sync-write packet, filled in place.

scservo_sdk's ``GroupSyncWrite`` rebuilds its parameter lists, a dict and a
Python list of ints on every write, then sums the packet byte by byte in
Python: on a core gone cold since the last palm step that is most of the
operator's per-stimulus cost after the inverse kinematics. The packet of a
goal write never changes shape (same servos, same register), so it is laid
out once and each write patches the value bytes and the checksum.

The bytes are exactly the SDK's (``tests/servos/test_sync_write.py`` checks
them against ``GroupSyncWrite`` for arbitrary goals) and go out through the
SDK's own port handler; reads, pings and the other writes stay on the SDK.

Packet: ``FF FF FE len 83 address size (id v0 v1 ...)* checksum``, where
``len`` counts the bytes after it and the checksum is the low byte of the
complement of the sum from the broadcast id to the last parameter.
"""

from __future__ import annotations

from collections.abc import Sequence

BROADCAST_ID = 0xFE
INST_SYNC_WRITE = 0x83


class SyncWritePacket:
    """The sync write of one 2-byte register to a fixed list of servos.

    ``big_endian``: the SCS series (the SDK's ``protocol_end`` 1); STS is little-endian.
    """

    def __init__(self, ids: Sequence[int], address: int, *, big_endian: bool = False) -> None:
        ids = [int(i) for i in ids]
        if not ids or len(set(ids)) != len(ids) or not all(0 <= i < BROADCAST_ID for i in ids):
            raise ValueError(f"a sync write needs distinct servo ids 0..253, got {ids}")
        if not 0 <= address <= 0xFF:
            raise ValueError(f"register address {address} does not fit a byte")
        self.ids = tuple(ids)
        n = len(ids)
        packet = bytearray([0xFF, 0xFF, BROADCAST_ID, 3 * n + 4, INST_SYNC_WRITE, address, 2])
        for sid in ids:
            packet += bytes([sid, 0, 0])
        packet.append(0)
        self._packet = packet
        self._fixed_sum = sum(packet[2:-1])  # everything but the values and the checksum
        #: where each servo's first value byte goes
        self._at = tuple(8 + 3 * k for k in range(n))
        self._big_endian = big_endian

    def __len__(self) -> int:
        return len(self._packet)

    def build(self, values: Sequence[int]) -> bytearray:
        """The packet for ``values`` (0..65535, in ``ids`` order); the buffer is reused."""
        packet, total = self._packet, self._fixed_sum
        if len(values) != len(self._at):
            raise ValueError(f"{len(values)} values for {len(self._at)} servos")
        for at, value in zip(self._at, values):  # noqa: B905 - lengths checked above
            if not 0 <= value <= 0xFFFF:
                raise ValueError(f"value {value} does not fit a 2-byte register")
            lo, hi = value & 0xFF, value >> 8
            if self._big_endian:
                lo, hi = hi, lo
            packet[at] = lo
            packet[at + 1] = hi
            total += lo + hi
        packet[-1] = ~total & 0xFF
        return packet
