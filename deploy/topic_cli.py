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
path's jitter and this process's stalls. Exit code 0 when something
arrived, 1 when nothing did (with what the connection says, on stderr).
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import json
import math
import sys
import threading
import time
from collections import Counter
from typing import Any, TextIO

import numpy as np

from common.clock import now_ns
from common.link_stats import SEQ_RESTART_GAP
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
#: a heartbeat counter with one of these in its name is a refusal the robot reports
REFUSAL_WORDS = ("refused", "rejected")
#: arrays of at most this many values are printed whole (a stimulus), larger ones summarized
WHOLE_ARRAY = 9
#: strings longer than this (a video offer's SDP) are cut when printed
LONG_TEXT = 120
#: fields holding a run's random session number, printed in hex
SESSION_FIELDS = ("session", "echo_session")
#: the rates and gaps leave out what arrived in this long after the first message: a process
#: that has just started reads its first messages late (its first decodes load code; a loaded
#: machine schedules it late), and their receive times come bunched
WARM_UP_S = 0.5
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


# ------------------------------------------------------------------- counting
@dataclasses.dataclass
class _Arrival:
    t_recv_ns: int
    seq: int
    t_send_ns: int
    session: int | None


class TopicWatch:
    """One robot's one topic: arrivals in the window, and totals since the start."""

    def __init__(self, window_ns: int | None) -> None:
        self.window_ns = window_ns
        self.recent: collections.deque[_Arrival] = collections.deque()
        self.count = 0
        self.bytes = 0
        self.lost = 0
        self.sessions: Counter[int | None] = Counter()
        self.signers: Counter[bytes | None] = Counter()
        self._last_seq: dict[int | None, int] = {}

    def add(self, got: Received, timed: bool = True) -> None:
        """``timed``: the arrival counts toward the rates (not during the tap's warm-up)."""
        msg = got.msg
        self.count += 1
        self.bytes += got.size
        self.sessions[msg.session] += 1
        self.signers[msg.signer] += 1
        last = self._last_seq.get(msg.session)
        self._last_seq[msg.session] = msg.seq
        if last is not None and 1 < msg.seq - last <= SEQ_RESTART_GAP:
            self.lost += msg.seq - last - 1
        if timed:
            self.recent.append(_Arrival(got.t_recv_ns, msg.seq, msg.t_send_ns, msg.session))

    def trim(self, now: int) -> None:
        if self.window_ns is None:
            return
        while self.recent and now - self.recent[0].t_recv_ns > self.window_ns:
            self.recent.popleft()

    def rates(self) -> dict[str, float | None]:
        """Over the window: the rates (the newest run's messages) and the receive gaps.

        ``rate_hz``: the messages that arrived, over the span of their send times (the
        sender's clock); ``sent_hz``: the messages sent, their seq span over the same. Timed
        by the sender's clock, neither bends when this process is late to read (a loaded
        machine ran it late, and the receive times of what waited came bunched: a rate over
        receive times read 15 % high, or twice the rate after a stall). What this process
        and the path did to the timing shows in the receive gaps.
        """
        out: dict[str, float | None] = {
            "rate_hz": None,
            "sent_hz": None,
            "gap_min_ms": None,
            "gap_max_ms": None,
        }
        recent = self.recent
        if len(recent) < 2:
            return out
        gaps = [b.t_recv_ns - a.t_recv_ns for a, b in zip(recent, list(recent)[1:], strict=False)]
        out["gap_min_ms"] = min(gaps) / 1e6
        out["gap_max_ms"] = max(gaps) / 1e6
        # the newest run's messages only: a restarted robot counts from 1 again
        run = [a for a in recent if a.session == recent[-1].session]
        span = max(a.t_send_ns for a in run) - min(a.t_send_ns for a in run)
        seqs = max(a.seq for a in run) - min(a.seq for a in run)
        if len(run) >= 2 and span > 0:
            out["rate_hz"] = (len(run) - 1) * 1e9 / span
            out["sent_hz"] = seqs * 1e9 / span
        return out


class RobotWatch:
    """One robot: its topics, and the refusals its heartbeats report."""

    def __init__(self, window_ns: int | None) -> None:
        self.window_ns = window_ns
        self.topics: dict[str, TopicWatch] = {}
        self.refusals_first: dict[str, float] = {}
        self.refusals: dict[str, float] = {}

    def add(self, got: Received, timed: bool = True) -> None:
        watch = self.topics.get(got.topic)
        if watch is None:
            watch = self.topics[got.topic] = TopicWatch(self.window_ns)
        watch.add(got, timed)
        stats = getattr(got.msg, "stats", None)
        if got.topic == "heartbeat" and stats:
            for key, value in stats.items():
                if any(word in key for word in REFUSAL_WORDS):
                    self.refusals_first.setdefault(key, value)
                    self.refusals[key] = value


class Watch:
    """Everything read, per robot and topic."""

    def __init__(self, window_s: float | None, robot_key: bytes | None = None) -> None:
        self.window_ns = None if window_s is None else round(window_s * 1e9)
        self.robot_key = robot_key
        self.robots: dict[bytes, RobotWatch] = {}
        self.t_start_ns = now_ns()
        self.messages = 0
        #: arrivals before this count, but are not timed (``WARM_UP_S``)
        self.timed_from_ns: int | None = None

    def add(self, got: Received) -> None:
        robot = self.robots.get(got.robot)
        if robot is None:
            robot = self.robots[got.robot] = RobotWatch(self.window_ns)
        if self.timed_from_ns is None:
            self.timed_from_ns = got.t_recv_ns + round(WARM_UP_S * 1e9)
        robot.add(got, got.t_recv_ns >= self.timed_from_ns)
        self.messages += 1

    def signer_name(self, signer: bytes | None) -> str:
        """``unsigned``, ``robot key`` (the one ``--robot-key`` names) or the key's first digits."""
        if signer is None:
            return "unsigned"
        if self.robot_key is not None:
            if signer == self.robot_key:
                return "robot key"
            return f"key {signer.hex()[:16]} (NOT the robot's)"
        return f"key {signer.hex()[:16]}"

    def report(self, topics: tuple[str, ...], rejected: Counter[str]) -> dict[str, Any]:
        now = now_ns()
        robots: dict[str, Any] = {}
        for name, robot in sorted(self.robots.items()):
            per_topic: dict[str, Any] = {}
            for topic in topics:
                watch = robot.topics.get(topic)
                if watch is None:
                    per_topic[topic] = {"count": 0}
                    continue
                watch.trim(now)
                per_topic[topic] = {
                    "count": watch.count,
                    "in_window": len(watch.recent),
                    **watch.rates(),
                    "lost": watch.lost,
                    "bytes_mean": round(watch.bytes / watch.count, 1),
                    "sessions": {_session(s): n for s, n in watch.sessions.items()},
                    "signers": {self.signer_name(k): n for k, n in watch.signers.items()},
                }
            robots[name.decode("ascii")] = {
                "topics": per_topic,
                "refusals": dict(sorted(robot.refusals.items())),
                "refusals_while_watching": {
                    k: v - robot.refusals_first[k]
                    for k, v in sorted(robot.refusals.items())
                    if v != robot.refusals_first[k]
                },
            }
        return {
            "elapsed_s": round((now - self.t_start_ns) / 1e9, 3),
            "window_s": None if self.window_ns is None else self.window_ns / 1e9,
            "robots": robots,
            "rejected": dict(rejected),
        }


def _session(session: int | None) -> str:
    return "none" if session is None else f"{session:016x}"


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
    from common.signals import stop_on_signals

    return watch(args, stop_on_signals())
