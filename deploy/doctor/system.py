"""The machine: CPU governor, real-time scheduling, the service user."""

from __future__ import annotations

import glob
import os
import threading
from pathlib import Path
from typing import Any

from common.devices.preflight import PASS, SKIP, WARN, user_named
from deploy.doctor.report import DoctorOptions, Report


def check_governor(report: Report) -> None:
    """A clock that ramps adds jitter to a 60 Hz loop."""
    files = sorted(glob.glob("/sys/devices/system/cpu/cpu[0-9]*/cpufreq/scaling_governor"))
    if not files:
        report.add(
            "cpu governor",
            SKIP,
            "no cpufreq interface (a VM, or a CPU at a fixed clock): nothing to set",
        )
        return
    governors: dict[str, list[str]] = {}
    for f in files:
        try:
            g = Path(f).read_text().strip()
        except OSError:
            continue
        governors.setdefault(g, []).append(f.split("/")[5])
    if set(governors) == {"performance"}:
        report.add("cpu governor", PASS, f"performance on all {len(files)} CPUs")
        return
    summary = "; ".join(f"{g} on {len(c)} CPU(s)" for g, c in governors.items())
    report.add(
        "cpu governor",
        WARN,
        f"{summary}: clock ramps add latency jitter to a 60 Hz loop",
        "`sudo cpupower frequency-set -g performance` (package linux-cpupower), made "
        "permanent as in docs/deploy.md",
    )


#: how long the doctor's keep-alive probe runs (``--keep-alive-probe``), and its period (the
#: arm's keep-alive's)
PROBE_S = DoctorOptions.keep_alive_probe_s
PROBE_PERIOD_S = 0.02
#: the UR controller's watchdog window (URArmConfig's default): a wake this late stops the arm
WATCHDOG_WINDOW_S = 0.15


def probe_keep_alive(priority: int, seconds: float = PROBE_S) -> tuple[Any, dict[str, float]]:
    """A thread scheduled as the arm process's keep-alive is (SCHED_FIFO ``priority`` where
    granted, else the safety niceness), waking every 20 ms for ``seconds``: what it got and
    how its period came out (common.process.realtime.PeriodStats)."""
    from common.clocks.clock import now_s
    from common.process.realtime import PeriodStats, raise_this_thread
    from robot_side.arm.base import SAFETY_THREAD_NICE

    out: dict[str, Any] = {}

    def run() -> None:
        out["got"] = raise_this_thread(priority, SAFETY_THREAD_NICE)
        stats = PeriodStats(PROBE_PERIOD_S)
        quit_ = threading.Event()
        due = now_s() + PROBE_PERIOD_S
        end = due + seconds
        while not quit_.wait(max(0.0, due - now_s())) and now_s() < end:
            stats.woke(now_s())
            due += PROBE_PERIOD_S
        out["summary"] = stats.summary()

    t = threading.Thread(target=run, name="doctor-keepalive-probe", daemon=True)
    t.start()
    t.join(seconds + 5)
    return out.get("got"), out.get("summary", {})


def check_realtime(
    report: Report, config: Any = None, role: str = "robot", probe_s: float = PROBE_S
) -> None:
    """Whether the arm's keep-alive gets real-time scheduling here, and how on time it runs.

    A probe thread is scheduled as the arm process schedules its keep-alive and
    wakes every 20 ms for two seconds beside whatever the machine is doing;
    the doctor reports what it got and its period's p99 and max. Run as the
    unit runs (``sudo -u deepxpalm``, or under ``systemd-run -p LimitRTPRIO=20``)
    to see what the unit gets: a shell's limits may differ from the unit's.
    """
    import resource

    if role != "robot":
        return  # the operator's palm has no watchdog of its own to keep quiet
    if not hasattr(os, "SCHED_FIFO"):
        report.add("real-time scheduling", SKIP, "this platform has no SCHED_FIFO")
        return
    if probe_s <= 0:
        report.add("real-time scheduling", SKIP, "not probed (--keep-alive-probe 0)")
        return
    arm = getattr(config, "arm", None) if config is not None else None
    priority = int(arm.get("realtime_priority", 20)) if isinstance(arm, dict) else 20
    soft, _hard = resource.getrlimit(resource.RLIMIT_RTPRIO)
    rlimit = "unlimited" if soft == resource.RLIM_INFINITY else str(soft)
    kernel = "PREEMPT_RT" if Path("/sys/kernel/realtime").exists() else "standard kernel"
    got, summary = probe_keep_alive(priority, probe_s)
    if got is None or not summary:
        report.add("real-time scheduling", WARN, "the keep-alive probe did not run")
        return
    timing = (
        f"a 20 ms keep-alive here woke with period p99 {summary['p99_ms']:.1f} ms, max "
        f"{summary['max_ms']:.1f} ms over {probe_s:g} s (the controller stops the arm at "
        f"{WATCHDOG_WINDOW_S * 1000:.0f} ms)"
    )
    detail = f"{got.describe()} (RLIMIT_RTPRIO {rlimit}, {kernel}): {timing}"
    late = summary["max_ms"] > WATCHDOG_WINDOW_S * 1000 / 2
    if got.realtime and not late:
        report.add("real-time scheduling", PASS, detail)
    elif got.realtime:
        report.add(
            "real-time scheduling",
            WARN,
            detail,
            "something on this PC runs ahead of real-time threads (another SCHED_FIFO "
            "program, an interrupt storm, throttling): see docs/arm.md, Real time",
        )
    else:
        report.add(
            "real-time scheduling",
            WARN,
            detail + "; without SCHED_FIFO a busy PC can hold the keep-alive past the "
            "window and the controller stops the arm",
            "the shipped robot unit grants it (LimitRTPRIO=20); for a shell add "
            "'deepxpalm - rtprio 20' to /etc/security/limits.d/deepxpalm.conf "
            "(docs/deploy.md, Real-time scheduling)",
        )


def check_service_user(report: Report, options: DoctorOptions) -> None:
    """The systemd units run as this user; its rights are what the doctor checks files against."""
    user = user_named(options.service_user)
    if user is None:
        report.add(
            "service user",
            SKIP,
            f"no user {options.service_user!r} (only the systemd units need it; "
            "deploy/systemd/deepxpalm.sysusers.conf makes it)",
        )
        return
    report.add(
        "service user",
        PASS,
        f"{options.service_user} exists (uid {user.pw_uid}); the units add dialout",
    )
