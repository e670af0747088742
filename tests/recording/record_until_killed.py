"""Child process for the SIGKILL test: records at a steady rate until it is killed.

Prints one line per chunk flush, ``flushed <records on disk> <monotonic ns>``,
so the parent knows what must survive; the records carry their index and
the time they were written.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from common.recording.mcap_recorder import McapRecorder


def main() -> None:
    path, rate_hz = sys.argv[1], float(sys.argv[2])
    rec = McapRecorder(path, flush_interval_s=1.0)
    frame = np.linspace(0, 9, 200, dtype=np.float32).reshape(2, 10, 10)
    period = 1.0 / rate_hz
    flushed = 0
    i = 0
    next_t = time.monotonic()
    while True:
        rec.write("robot/frame", time.monotonic_ns(), {"frame": frame, "frame_seq": i})
        i += 1
        if rec.records_flushed != flushed:
            flushed = rec.records_flushed
            print(f"flushed {flushed} {time.monotonic_ns()}", flush=True)
        next_t += period
        time.sleep(max(0.0, next_t - time.monotonic()))


if __name__ == "__main__":
    main()
