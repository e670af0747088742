"""``deepxpalm topic``: look at the wire, as ``ros2 topic hz`` and ``echo`` do.

It reads a robot's telemetry with the user's own keys (``deploy/wire_tap.py``:
a robot's direct link with CURVE, or the fabric's router with a certificate),
sends nothing, and prints per robot and topic (``stimulus``, ``frame``,
``heartbeat``, ``video``):

- ``list`` (the default): a few seconds' listening, then each topic's rate,
  the sessions (the robot's runs: a new one is a restart), who signed, and
  the refusals the robot reports in its heartbeats (its counters named
  ``*refused*`` and ``*rejected*``);
- ``hz``: the same table every second over a sliding window, with the
  smallest and largest gap between two messages;
- ``echo``: every message, decoded by the codec (arrays summarized).

Rates: ``rate`` is what arrived here, ``sent`` what the robot sent (its
sequence numbers), both per second of the robot's own clock (the messages'
send times), so neither bends when this process reads late: a ``sent``
above ``rate`` is loss on the way, a ``sent`` below what the robot should
send is the robot's own doing; the gaps between receive times show the
path's jitter and this process's stalls (``deploy/topic_watch.py`` counts;
this module reads and prints). Exit code 0 when something arrived, 1 when
nothing did (with what the connection says, on stderr).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import threading
import time
from typing import Any, TextIO

import numpy as np

from deploy.topic_watch import Watch
from deploy.wire_tap import TOPICS, Received, TapConfig, WireTap, add_link_arguments, tap_config

EPILOG = """\
Reads a robot's telemetry with your own keys and sends nothing. Per robot and topic:
  list  (the default) listen 3 s, then each topic's rate, the sessions (the robot
        node's runs), who signed, and the refusals the robot's heartbeat reports
        (its counters named *refused* or *rejected*)
  hz    the same every second over --window seconds, with the smallest and the
        largest gap between two messages
  echo  every message, decoded and checked as a node checks it (arrays summarized)

"rate" is what arrived here, "sent" what the robot sent (its sequence numbers), both
per second of the robot's own clock: a "sent" above "rate" is loss on the way; "gap"
is between two receive times here. Exit code 1 when nothing arrived, with what the
connection says. docs/deploy.md, "Look at the wire".
"""
#: arrays of at most this many values are printed whole (a stimulus), larger ones summarized
WHOLE_ARRAY = 9
#: strings longer than this (a video offer's SDP) are cut when printed
LONG_TEXT = 120
#: fields holding a run's random session number, printed in hex
SESSION_FIELDS = ("session", "echo_session")
#: how long ``list`` listens by default, s: a heartbeat's counters come once a second on the
#: fabric, so three give rates over two intervals at least
LIST_SECONDS = 3.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = EPILOG
    parser.add_argument(
        "action",
        nargs="?",
        choices=("list", "hz", "echo"),
        default="list",
        help="list: listen a few seconds and sum up (default); hz: rates every second; "
        "echo: every message decoded",
    )
    parser.add_argument(
        "--topic",
        action="append",
        default=[],
        choices=sorted(TOPICS),
        help="only this topic (repeatable); default: all of them",
    )
    parser.add_argument(
        "--count",
        type=int,
        help="stop after this many messages (echo, list) or reports (hz)",
    )
    parser.add_argument(
        "--duration",
        type=float,
        help=f"stop after this many seconds (list: {LIST_SECONDS:g} unless --count; "
        "hz and echo: until Ctrl-C)",
    )
    parser.add_argument(
        "--window", type=float, default=5.0, help="hz: the rates over this many seconds"
    )
    parser.add_argument(
        "--json", action="store_true", help="one JSON object per message (echo) or report"
    )
    add_link_arguments(parser)


# ----------------------------------------------------------------- printing
def _num(v: float | None, fmt: str) -> str:
    return "-" if v is None else format(v, fmt)


def table(report: dict[str, Any]) -> str:
    """A report as the terminal shows it: a row per robot and topic, then sessions and refusals."""
    head = f"{'robot':<12} {'topic':<10} {'rate Hz':>8} {'sent Hz':>8} {'gap ms':>13} "
    head += f"{'msgs':>6} {'lost':>5}  signed"
    window = report["window_s"]
    title = f"-- {report['elapsed_s']:.1f} s" + (f", window {window:g} s --" if window else " --")
    lines = [title, head]
    if not report["robots"]:
        lines.append("(no message)")
    for name, robot in report["robots"].items():
        label = name or "(unnamed)"
        sessions: dict[str, list[str]] = {}
        for topic, t in robot["topics"].items():
            if not t["count"]:
                lines.append(f"{label:<12} {topic:<10} {'-':>8} {'-':>8} {'-':>13} {0:>6} {'-':>5}")
                continue
            gap = (
                "-" if t["gap_min_ms"] is None else f"{t['gap_min_ms']:.1f}..{t['gap_max_ms']:.1f}"
            )
            signed = ", ".join(
                f"{k} x{n}" if len(t["signers"]) > 1 else k for k, n in t["signers"].items()
            )
            lines.append(
                f"{label:<12} {topic:<10} {_num(t['rate_hz'], '8.2f')} "
                f"{_num(t['sent_hz'], '8.2f')} {gap:>13} {t['count']:>6} {t['lost']:>5}  {signed}"
            )
            for session in t["sessions"]:
                sessions.setdefault(session, []).append(topic)
        for session, topics in sessions.items():
            lines.append(f"{label:<12} session {session} ({', '.join(topics)})")
        if len(sessions) > 1:
            lines.append(f"{label:<12} several sessions: the robot node restarted while watched")
        refusals = robot["refusals"]
        if refusals:
            grown = robot["refusals_while_watching"]
            said = ", ".join(
                f"{k} {v:g}" + (f" (+{grown[k]:g} while watching)" if k in grown else "")
                for k, v in refusals.items()
                if v or k in grown
            )
            lines.append(f"{label:<12} refusals: {said or 'none'} (its heartbeat's counters)")
        elif robot["topics"].get("heartbeat", {}).get("count"):
            lines.append(f"{label:<12} refusals: none reported (its heartbeat's counters)")
    if report["rejected"]:
        said = ", ".join(f"{k} {v}" for k, v in sorted(report["rejected"].items()))
        lines.append(f"refused here (the codec): {said}")
    return "\n".join(lines) + "\n"


def summarize(value: Any) -> Any:
    """A field as ``echo`` shows it: small arrays whole, large ones as their shape and range,
    bytes in hex, a long text cut."""
    if isinstance(value, np.ndarray):
        if value.size <= WHOLE_ARRAY:
            return np.round(value.astype(float), 4).tolist()
        finite = value[np.isfinite(value)] if value.dtype.kind == "f" else value
        return {
            "dtype": str(value.dtype),
            "shape": list(value.shape),
            "min": round(float(finite.min()), 4) if finite.size else None,
            "max": round(float(finite.max()), 4) if finite.size else None,
            "mean": round(float(finite.mean()), 4) if finite.size else None,
        }
    if isinstance(value, (bytes, bytearray)):
        return bytes(value).hex()
    if isinstance(value, tuple):
        return [summarize(v) for v in value]
    if isinstance(value, dict):
        return {k: summarize(v) for k, v in sorted(value.items())}
    if isinstance(value, str) and len(value) > LONG_TEXT:
        return f"{value[:LONG_TEXT]}... ({len(value)} characters)"
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def echo_record(got: Received, watch: Watch) -> dict[str, Any]:
    """One message as ``echo --json`` prints it."""
    fields: dict[str, Any] = {}
    for f in dataclasses.fields(got.msg):
        value = getattr(got.msg, f.name)
        if value is None or (f.name == "defects" and not value):
            continue
        fields[f.name] = summarize(value)
    return {
        "robot": got.robot.decode("ascii"),
        "topic": got.topic,
        "t_recv_wall": round(time.time(), 6),
        "bytes": got.size,
        "signed": watch.signer_name(got.msg.signer),
        "fields": fields,
    }


def _yaml_lines(key: str, value: Any, indent: str) -> list[str]:
    if isinstance(value, dict) and not {"dtype", "shape"} <= set(value):
        lines = [f"{indent}{key}:"]
        for k, v in value.items():
            lines += _yaml_lines(k, v, indent + "  ")
        return lines
    if isinstance(value, dict):  # a summarized array
        shape = "x".join(map(str, value["shape"]))
        return [
            f"{indent}{key}: {value['dtype']} {shape}, min {value['min']} max {value['max']} "
            f"mean {value['mean']}"
        ]
    if key in SESSION_FIELDS and isinstance(value, int):
        return [f"{indent}{key}: {value:016x}"]
    return [f"{indent}{key}: {json.dumps(value) if isinstance(value, str) else value}"]


def echo_text(record: dict[str, Any]) -> str:
    """One message as ``echo`` prints it, in the manner of ``ros2 topic echo``."""
    stamp = time.strftime("%H:%M:%S", time.localtime(record["t_recv_wall"]))
    millis = int(record["t_recv_wall"] * 1000) % 1000
    robot = record["robot"] or "(unnamed)"
    lines = [
        f"--- {robot} {record['topic']}  {stamp}.{millis:03d}  {record['bytes']} B  "
        f"{record['signed']}"
    ]
    for key, value in record["fields"].items():
        lines += _yaml_lines(key, value, "")
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------- run
def watch(
    args: argparse.Namespace,
    stop: threading.Event,
    out: TextIO = sys.stdout,
    err: TextIO = sys.stderr,
    *,
    config: TapConfig | None = None,
) -> int:
    """Read and print as ``args`` asks until ``stop``, ``--count`` or ``--duration``."""
    cfg = tap_config(args) if config is None else config
    topics = tuple(dict.fromkeys(args.topic)) or tuple(TOPICS)
    duration = args.duration
    if args.action == "list" and duration is None and args.count is None:
        duration = LIST_SECONDS
    tap = WireTap(cfg, topics)
    watch = Watch(args.window if args.action == "hz" else None, cfg.robot_key)
    print(f"reading {', '.join(topics)} from {tap.connection()['via']}", file=err, flush=True)
    t_end = None if duration is None else time.monotonic() + duration
    next_report = time.monotonic() + 1.0
    reports = 0
    try:
        while not stop.is_set():
            now = time.monotonic()
            if t_end is not None and now >= t_end:
                break
            wait = min(0.1, max(0.0, (t_end or math.inf) - now), max(0.0, next_report - now))
            for got in tap.read(wait):
                watch.add(got)
                if args.action == "echo":
                    record = echo_record(got, watch)
                    out.write(json.dumps(record) + "\n" if args.json else echo_text(record))
                    out.flush()
                    if args.count is not None and watch.messages >= args.count:
                        stop.set()
                        break
            if args.action == "list" and args.count is not None and watch.messages >= args.count:
                break
            if args.action == "hz" and time.monotonic() >= next_report:
                next_report += 1.0
                _print_report(watch.report(topics, tap.rejected), args.json, out)
                reports += 1
                if args.count is not None and reports >= args.count:
                    break
        if args.action == "list":
            _print_report(watch.report(topics, tap.rejected), args.json, out)
        if not watch.messages:
            print(f"nothing arrived: {tap.why_nothing()}", file=err, flush=True)
            return 1
        return 0
    finally:
        tap.close()


def _print_report(report: dict[str, Any], as_json: bool, out: TextIO) -> None:
    out.write(json.dumps(report) + "\n" if as_json else table(report))
    out.flush()


def run(args: argparse.Namespace) -> int:
    from common.process.signals import stop_on_signals

    return watch(args, stop_on_signals())
