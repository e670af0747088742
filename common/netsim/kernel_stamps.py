"""When a packet reached the kernel: Linux receive stamps, for the stream and datagram modes.

The forwarders delay each chunk from its arrival, not from when their
thread got round to reading it; on a busy machine the two differ by
milliseconds, and the kernel's ``SO_TIMESTAMPNS`` stamp is the arrival.
"""

from __future__ import annotations

import socket
import struct
import time

#: Linux's SO_TIMESTAMPNS (and SCM_TIMESTAMPNS); Python's socket module lacks it.
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)
_TIMESPEC = struct.Struct("qq")
#: ancillary buffer size ``recvmsg`` needs for one stamp
ANC_BYTES = socket.CMSG_SPACE(_TIMESPEC.size)


def arrival_ns(anc: list[tuple[int, int, bytes]], t_read: int, real_minus_mono: int) -> int:
    """When the chunk reached the kernel (its receive timestamp), on the monotonic clock."""
    for level, kind, payload in anc:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
            sec, nsec = _TIMESPEC.unpack_from(payload)
            at = sec * 1_000_000_000 + nsec - real_minus_mono
            if t_read - 1_000_000_000 < at <= t_read:  # ignore a wall-clock step
                return at
    return t_read


def real_minus_mono_ns(tries: int = 50) -> int:
    """The wall clock minus the monotonic one, never above the truth.

    Read between two monotonic reads, the wall clock's offset lies between
    ``real - after`` and ``real - before``; the tightest lower bound of a few
    tries errs by well under a microsecond, towards a later arrival. A
    kernel stamp converted with it is never earlier than the packet came.
    """
    best_gap, best = None, 0
    for _ in range(tries):
        before = time.monotonic_ns()
        real = time.time_ns()
        after = time.monotonic_ns()
        if best_gap is None or after - before < best_gap:
            best_gap, best = after - before, real - after
    return best
