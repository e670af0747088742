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
RENDER_STAGES = ("sanitize_contact", "classification", "render", "encode")


def modelled(
    stage_medians_us: dict[str, float],
    transit_send_us: float,
    rates: tuple[float, ...],
    cap_hz: float,
) -> list[dict[str, Any]]:
    """CPU microseconds per second of one stream, and streams per core, from stage medians."""
    read = sum(stage_medians_us.get(s, 0.0) for s in READ_STAGES)
    stages = RENDER_STAGES
    if "frame_step" in stage_medians_us:  # the node's path: one compiled call for three
        stages = ("frame_step", "encode")
    render = sum(stage_medians_us.get(s, 0.0) for s in stages) + transit_send_us
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
    decompose: bool = True,
) -> list[dict[str, Any]]:
    """The robot node alone (no operator) at each rate, capped and uncapped.

    ``decompose`` adds two runs that split the node's cost: frames with no
    contact at the first rate (read, never classified) and a board sending
    2 scans per second (the node's fixed cost: heartbeats, timeouts).
    """
    runs: list[tuple[str, list[np.ndarray], float, float, str | None]] = []
    for rate in rates:
        for capped in (True, False):
            for backend in backends if (capped and rate == rates[0]) else (None,):
                runs.append(("demo scene", frames, rate, cap_hz if capped else rate, backend))
    if decompose:
        empty = [np.zeros_like(frames[0])]
        runs.append(("no contact", empty, rates[0], cap_hz, None))
        runs.append(("idle (2 scans/s)", empty, 2.0, cap_hz, None))
    rows = []
    for content, fr, rate, publish, backend in runs:
        r = run_nodes(
            fr,
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
                "content": content,
                "rate_hz": rate,
                "publish_rate_hz": publish,
                "backend": r["backend"],
                "cpu_percent": cpu,
                "streams_per_core": int(100 // cpu) if cpu > 0 else None,
                "scans_per_s": r["scans_per_s"],
                "window_per_s": r.get("robot_window_per_s", {}),
                "threads_percent": r.get("robot_threads_percent", {}),
                "stats": r.get("robot_stats", {}),
            }
        )
        log.info("robot node, %s at %s Hz (cap %s): %.1f %% CPU", content, rate, publish, cpu)
    return rows
