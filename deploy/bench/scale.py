"""Scale: the robot node's cost against frame rate, and sensor streams per core.

Two views that check each other:

- measured: the robot node as a process on a pty board at 120, 500 and
  1000 Hz, with the default 60 Hz render cap and with every frame
  rendered; CPU time per second of wall time from /proc;
- modelled: per-frame stage medians from the latency budget. Every frame
  is read (decode + calibration); at most ``publish_rate_hz`` of them are
  rendered (sanitize, classify, downsize, mask, encode, send). One core
  serves as many streams as fit in a second of its time.

The model leaves out the node's fixed costs (heartbeats, the event loop,
the reader thread's wake-ups), which the measurement includes: their
difference is that overhead.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from deploy.bench.nodecpu import run_nodes

log = logging.getLogger(__name__)

READ_STAGES = ("wire_decode", "calibration")
RENDER_STAGES = ("sanitize_contact", "classification", "downsizing", "masking", "encode")


def modelled(
    stage_medians_us: dict[str, float],
    transit_send_us: float,
    rates: tuple[float, ...],
    cap_hz: float,
) -> list[dict[str, Any]]:
    """CPU microseconds per second of one stream, and streams per core, from stage medians."""
    read = sum(stage_medians_us.get(s, 0.0) for s in READ_STAGES)
    render = sum(stage_medians_us.get(s, 0.0) for s in RENDER_STAGES) + transit_send_us
    rows = []
    for rate in rates:
        for capped in (True, False):
            rendered = min(rate, cap_hz) if capped else rate
            us_per_s = rate * read + rendered * render
            rows.append(
                {
                    "rate_hz": rate,
                    "capped": capped,
                    "rendered_per_s": rendered,
                    "cpu_percent": us_per_s / 1e4,
                    "streams_per_core": int(1e6 // us_per_s) if us_per_s > 0 else None,
                }
            )
    return rows


def measured(
    frames: list[np.ndarray],
    rates: tuple[float, ...],
    warmup_s: float,
    measure_s: float,
    cap_hz: float,
    backends: tuple[str | None, ...] = (None,),
) -> list[dict[str, Any]]:
    """The robot node alone (no operator) at each rate, capped and uncapped."""
    rows = []
    for rate in rates:
        for capped in (True, False):
            for backend in backends if (capped and rate == rates[0]) else (None,):
                publish = cap_hz if capped else rate
                r = run_nodes(
                    frames,
                    rate,
                    warmup_s,
                    measure_s,
                    publish_rate_hz=publish,
                    backend=backend,
                    with_operator=False,
                )
                cpu = r["robot_cpu_percent"]
                rows.append(
                    {
                        "rate_hz": rate,
                        "publish_rate_hz": publish,
                        "backend": r["backend"],
                        "cpu_percent": cpu,
                        "streams_per_core": int(100 // cpu) if cpu > 0 else None,
                        "scans_per_s": r["scans_per_s"],
                        "window_per_s": r.get("robot_window_per_s", {}),
                        "stats": r.get("robot_stats", {}),
                    }
                )
                log.info("robot node at %s Hz (render cap %s): %.1f %% CPU", rate, publish, cpu)
    return rows
