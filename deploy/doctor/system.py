"""The machine: CPU governor, real-time scheduling, the service user."""

from __future__ import annotations

import glob
import os
import threading
from pathlib import Path
from typing import Any

from common.preflight import PASS, SKIP, WARN, user_named
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


def _can_use_fifo() -> tuple[bool, str]:
    """Try SCHED_FIFO priority 1 on a throwaway thread (the policy is per thread on Linux)."""
    result: dict[str, Any] = {}

    def probe() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
            result["ok"] = True
        except OSError as e:
            result["ok"], result["why"] = False, e.strerror or str(e)

    t = threading.Thread(target=probe, name="doctor-rt-probe", daemon=True)
    t.start()
    t.join(2)
    return bool(result.get("ok")), result.get("why", "")


def check_realtime(report: Report) -> None:
    """Whether the real-time drop-in can work here (only a warning: the units do not need it)."""
    import resource

    if not hasattr(os, "SCHED_FIFO"):
        report.add("real-time scheduling", SKIP, "this platform has no SCHED_FIFO")
        return
    max_prio = os.sched_get_priority_max(os.SCHED_FIFO)
    soft, _hard = resource.getrlimit(resource.RLIMIT_RTPRIO)
    ok, why = _can_use_fifo()
    kernel = "PREEMPT_RT" if Path("/sys/kernel/realtime").exists() else os.uname().version
    rt_kernel = "PREEMPT_RT" in kernel
    try:
        runtime = int(Path("/proc/sys/kernel/sched_rt_runtime_us").read_text())
    except (OSError, ValueError):
        runtime = None
    rlimit = "unlimited" if soft == resource.RLIM_INFINITY else str(soft)
    detail = (
        f"SCHED_FIFO priorities 1..{max_prio}, RLIMIT_RTPRIO {rlimit}, "
        f"{'PREEMPT_RT kernel' if rt_kernel else 'standard kernel'}"
        + (f", RT throttling {runtime} us/s" if runtime is not None else "")
    )
    if ok:
        report.add("real-time scheduling", PASS, f"{detail}: this user can use SCHED_FIFO")
    else:
        report.add(
            "real-time scheduling",
            WARN,
            f"{detail}: this user cannot use SCHED_FIFO ({why}); the units run with Nice=-10",
            "only needed for the real-time drop-in in docs/deploy.md (systemd sets the policy "
            "itself); for a shell session add '@dialout - rtprio 50' to "
            "/etc/security/limits.d/deepxpalm.conf",
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
