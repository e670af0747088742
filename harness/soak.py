"""``deepxpalm soak``: run the demo for a long time on a bad link and report how it aged.

The demo runs as a child process (the operator node in it, the robot node
and the link simulator as its children), recording both nodes. Every
``--sample-s`` the resident memory and CPU time of each of the three
processes are read from ``/proc``. At the end the demo's own summary gives
the message counts, and the recordings are read back to look for any
non-finite value or out-of-limit servo count and replayed through the
pipeline. One JSON report; exit status 1 when a limit is broken.

Linux only (``/proc``), like the robot PC.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import signal
import subprocess
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from common.process.command_line import add_overrides_argument
from common.progress import Progress
from deploy.units.readiness import NotReady
from deploy.units.service import Service
from harness.processes import children_of, cmdline, cpu_s, rss_mb

log = logging.getLogger(__name__)

MAX_GROWTH_MB = 20.0  # memory growth allowed over the soak


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--minutes", type=float, default=30.0, help="how long (default 30)")
    parser.add_argument("--scenario", default="bad_day", help="network scenario (default bad_day)")
    parser.add_argument("--scene", default="demo", help="scene name or TOML (default demo)")
    add_overrides_argument(parser, "robot.render.mode=mask_ground_truth")
    parser.add_argument(
        "--sample-s", type=float, default=10.0, help="seconds between memory samples (default 10)"
    )
    parser.add_argument(
        "--startup-s",
        type=float,
        default=30.0,
        help="memory growth is measured from here, after imports and connections (default 30)",
    )
    parser.add_argument(
        "--warmup-s",
        type=float,
        default=120.0,
        help="growth is also reported from this point on, after bounded buffers fill (default 120)",
    )
    parser.add_argument(
        "--dir", type=Path, help="where recordings and logs go (default: a temp dir)"
    )
    parser.add_argument("--out", type=Path, help="also write the JSON report here")
    parser.add_argument(
        "--no-replay", action="store_true", help="skip replaying the recordings at the end"
    )


def _role(pid: int) -> str | None:
    argv = cmdline(pid)
    if argv is None:
        return None
    for role in ("robot", "netsim"):
        if role in argv:
            return role
    return None


@dataclass
class Series:
    """One process's samples: (seconds since start, RSS MB, CPU seconds)."""

    pid: int
    samples: list[tuple[float, float, float]] = field(default_factory=list)

    def report(self, startup_s: float, warmup_s: float) -> dict[str, Any]:
        """Growth from the first sample after start-up (imports, connections) to the last."""
        t = np.array([s[0] for s in self.samples])
        started = t >= startup_s
        if started.sum() < 2:
            return {"pid": self.pid, "samples": int(started.sum())}
        rss = np.array([s[1] for s in self.samples])
        cpu = np.array([s[2] for s in self.samples])
        after = t >= warmup_s
        t0, rss0, cpu0 = t[started][0], rss[started][0], cpu[started][0]
        out: dict[str, Any] = {
            "pid": self.pid,
            "samples": len(t),
            "rss_at_startup_mb": round(float(rss0), 2),
            "rss_last_mb": round(float(rss[-1]), 2),
            "rss_max_mb": round(float(rss.max()), 2),
            "growth_mb": round(float(rss[-1] - rss0), 2),
            "growth_max_mb": round(float(rss[started].max() - rss0), 2),
            "cpu_percent": round(100 * float(cpu[-1] - cpu0) / max(t[-1] - t0, 1e-9), 2),
        }
        if after.sum() >= 2:
            ta, ra = t[after], rss[after]
            slope = np.polyfit(ta, ra, 1)[0] if ta[-1] > ta[0] else 0.0
            out["growth_after_warmup_mb"] = round(float(ra[-1] - ra[0]), 2)
            out["slope_after_warmup_mb_per_hour"] = round(float(slope) * 3600, 3)
        out["series"] = [[round(a, 1), round(b, 2), round(c, 2)] for a, b, c in self.samples]
        return out


# ------------------------------------------------------------------ checks
def scan_recording(path: Path) -> dict[str, Any]:
    """Every number in a recording finite, every servo count inside its limits."""
    from common.recording.mcap_recorder import RecordingReader
    from common.wire.codec import DecodeError, decode

    out: dict[str, Any] = {"records": 0, "nonfinite_values": 0, "servo_goals_out_of_limits": 0}
    states: dict[str, int] = {}
    if not path.exists():
        out["missing"] = True
        return out
    limits = None
    if "operator" in path.name:
        from common.recording.mcap_recorder import read_metadata
        from deploy.replay import calibration_for, recorded_config

        cal = calibration_for(recorded_config(read_metadata(path), "operator"), None)
        limits = (cal.min_counts, cal.max_counts)
    reader = RecordingReader(path)
    for channel, _, record in reader:
        out["records"] += 1
        if "_nonfinite" in record:
            out["nonfinite_values"] += len(record["_nonfinite"])
        if isinstance(record.get("wire"), bytes):
            try:
                msg = decode(record["wire"])  # validates: finite and in range, or it raises
            except DecodeError:
                out["nonfinite_values"] += 1
                continue
            del msg
        if channel == "operator/servo_goals" and limits is not None:
            counts = np.asarray(record["counts"])
            if not np.all((counts >= limits[0]) & (counts <= limits[1])):
                out["servo_goals_out_of_limits"] += 1
            if not np.all(np.isfinite(np.asarray(record["angles"], dtype=float))):
                out["nonfinite_values"] += 1
        if channel == "robot/frame" and not np.all(np.isfinite(record["frame"])):
            out["nonfinite_values"] += 1
        if channel.endswith("/link"):
            states[str(record.get("state"))] = states.get(str(record.get("state")), 0) + 1
    total = sum(states.values())
    if total:  # link records come at the heartbeat rate: shares of samples are shares of time
        out["link_state_share"] = {k: round(v / total, 4) for k, v in sorted(states.items())}
    out["closed_cleanly"] = reader.complete
    out["bytes"] = path.stat().st_size
    return out


def _log_problems(directories: list[Path]) -> dict[str, Any]:
    """ERROR lines and tracebacks in the demo's logs (the operator's, the robot's, netsim's)."""
    counts = {"error_lines": 0, "tracebacks": 0, "warning_lines": 0}
    examples: list[str] = []
    paths = [p for d in directories if d.exists() for p in sorted(d.glob("*.log"))]
    for path in paths:
        for line in path.read_text(errors="replace").splitlines():
            if " ERROR " in line or " CRITICAL " in line:
                counts["error_lines"] += 1
                if len(examples) < 5:
                    examples.append(f"{path.name}: {line[:200]}")
            elif "Traceback" in line:
                counts["tracebacks"] += 1
            elif " WARNING " in line:
                counts["warning_lines"] += 1
    return {**counts, "examples": examples}


# --------------------------------------------------------------------- run
def run(args: argparse.Namespace) -> int:
    duration_s = args.minutes * 60
    workdir = args.dir or Path(tempfile.mkdtemp(prefix="deepxpalm-soak-"))
    workdir.mkdir(parents=True, exist_ok=True)
    rec_dir = workdir / "recording"
    cmd = [
        "-v",
        "demo",
        "--json",
        "--duration",
        str(duration_s),
        "--scene",
        args.scene,
        "--scenario",
        args.scenario,
        "--record",
        str(rec_dir),
        # per-message faults, corruption included, so the decoders are exercised: message mode
        # re-publishes messages, which a CURVE link refuses, so the soak's link is plain
        "--plain",
        "--set",
        "network.mode=message",
    ]
    for override in args.overrides:
        cmd += ["--set", override]
    out_path, err_path = workdir / "demo.json", workdir / "demo.log"
    print(f"soak: {args.minutes:g} min of the demo on {args.scenario!r}; files in {workdir}")
    out_path.unlink(missing_ok=True)
    err_path.unlink(missing_ok=True)
    demo = Service("demo", cmd, err_path, stdout=out_path)
    demo.start()
    series: dict[str, Series] = {"operator (demo)": Series(demo.pid)}
    t0 = time.monotonic()
    deadline = t0 + duration_s + 120  # the demo stops itself; this is the backstop
    # the project's one bar (common/progress.py): redrawn on a terminal, a line a tenth in a log
    bar = Progress("soak", duration_s, unit="s")
    bar.update(0, detail="starting the demo", force=True)

    def tick() -> None:
        bar.update(min(time.monotonic() - t0, duration_s))

    try:
        with contextlib.suppress(NotReady):  # a demo that fails says why in its summary
            demo.wait_ready()  # every process of it up: its children are the ones to watch
        while demo.alive():
            elapsed = time.monotonic() - t0
            for pid in children_of(demo.pid):
                role = _role(pid)
                if role is not None and role not in series:
                    series[role] = Series(pid)
            for s in series.values():
                rss, cpu = rss_mb(s.pid), cpu_s(s.pid)
                if rss is not None and cpu is not None:
                    s.samples.append((elapsed, rss, cpu))
            rss = sum(s.samples[-1][1] for s in series.values() if s.samples)
            bar.update(detail=f"{len(series)} processes, {rss:.0f} MB", draw=False)
            tick()
            if time.monotonic() > deadline:
                log.error("the demo overran its duration by 2 minutes; stopping it")
                break
            _sleep_until_exit(demo.popen, args.sample_s, tick)
    except KeyboardInterrupt:
        pass
    finally:
        bar.close()
        demo.stop(60, signal.SIGINT, group=True)  # Ctrl-C to it and its children, as a user
        demo.close()
    returncode = demo.popen.returncode
    elapsed = time.monotonic() - t0
    summary: dict[str, Any] = {}
    with contextlib.suppress(OSError, ValueError):
        summary = json.loads(out_path.read_text())
    report = _report(args, elapsed, returncode, summary, series, workdir, rec_dir)
    text = json.dumps(report, indent=2)
    if args.out:
        args.out.write_text(text + "\n")
    (workdir / "soak.json").write_text(text + "\n")
    print(text)
    return 0 if report["passed"] else 1


def _sleep_until_exit(
    proc: subprocess.Popen, seconds: float, tick: Callable[[], None] | None = None
) -> None:
    """Until ``proc`` ends or ``seconds`` pass; ``tick`` (the progress bar) each second."""
    end = time.monotonic() + seconds
    while (left := end - time.monotonic()) > 0:
        try:
            proc.wait(timeout=min(left, 1.0) if tick is not None else left)
            return
        except subprocess.TimeoutExpired:
            if tick is not None:
                tick()


def _report(
    args: argparse.Namespace,
    elapsed: float,
    returncode: int,
    summary: dict[str, Any],
    series: dict[str, Series],
    workdir: Path,
    rec_dir: Path,
) -> dict[str, Any]:
    processes = {name: s.report(args.startup_s, args.warmup_s) for name, s in series.items()}
    recordings = {p.stem: scan_recording(p) for p in sorted(rec_dir.glob("*.mcap"))}
    replays: dict[str, Any] = {}
    if not args.no_replay:
        from deploy.replay import check

        for p in sorted(rec_dir.glob("*.mcap")):
            if p.name.startswith("camera"):  # the video server's pictures: nothing to replay
                continue
            s = check(p)
            replays[p.stem] = {
                k: s[k] for k in ("mismatches", "mismatch_kinds", "checked", "examples")
            }
    log_dirs = [workdir] + ([Path(summary["logs"])] if summary.get("logs") else [])
    logs = _log_problems(log_dirs)
    netsim = summary.get("netsim", {})
    published = summary.get("stimuli_published", 0) + summary.get("keyframes_published", 0)
    received = summary.get("stimuli_received", 0)
    crashes = list(summary.get("errors", [])) if summary else ["the demo printed no summary"]
    if returncode != 0:
        crashes.append(f"the demo exited with {returncode}")
    nonfinite = sum(r.get("nonfinite_values", 0) for r in recordings.values())
    out_of_limits = sum(r.get("servo_goals_out_of_limits", 0) for r in recordings.values())
    growth = {
        name: p.get("growth_mb", math.nan) for name, p in processes.items() if p.get("samples")
    }
    passed = (
        not crashes
        and nonfinite == 0
        and out_of_limits == 0
        and len(growth) == 3
        and all(g < MAX_GROWTH_MB for g in growth.values())
    )
    return {
        "passed": passed,
        "criteria": {
            "memory_growth_below_mb": MAX_GROWTH_MB,
            "crashes": 0,
            "nonfinite_values": 0,
            "servo_goals_out_of_limits": 0,
        },
        "minutes": round(elapsed / 60, 2),
        "scenario": args.scenario,
        "render_mode": summary.get("render_mode"),
        "crashes": crashes,
        "error_lines": logs.get("error_lines", 0),
        "memory_growth_mb": growth,
        "nonfinite_values": nonfinite,
        "servo_goals_out_of_limits": out_of_limits,
        "messages": {
            "stimuli_sent": published,
            "stimuli_received": received,
            "stimuli_lost": max(0, published - received),
            "rejected_by_operator": summary.get("rejected_messages", {}).get("operator"),
            "rejected_by_robot": summary.get("rejected_messages", {}).get("robot"),
            "servo_writes": summary.get("servo_writes"),
            "lift_offs": summary.get("lift_offs"),
            "latency_ms": summary.get("latency_ms"),
            "pattern_match": summary.get("pattern_match"),
            "netsim": netsim,
        },
        "link_state_share": {n: r.get("link_state_share") for n, r in recordings.items()},
        "recorder": {
            name: {k: r.get(k) for k in ("records", "bytes", "closed_cleanly")}
            for name, r in recordings.items()
        },
        "replay": replays,
        "logs": logs,
        "processes": processes,
        "files": str(workdir),
    }
