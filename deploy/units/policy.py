"""What systemd does when a shipped unit's process ends: read from deploy/systemd/*.service.

The fault matrix and `deepxpalm demo` restart a process when and as late as systemd
would on the deployed machine, so "recovers with no human" means the same
in the table as in the field.
"""

from __future__ import annotations

import contextlib
import os
import re
import shlex
import signal
from dataclasses import dataclass
from pathlib import Path

UNITS_DIR = Path(__file__).resolve().parents[1] / "systemd"

#: signals systemd counts as a clean end (systemd.service, "Restart=")
_CLEAN_SIGNALS = {signal.SIGHUP, signal.SIGINT, signal.SIGTERM, signal.SIGPIPE}


@dataclass(frozen=True)
class RestartPolicy:
    """A unit's Restart=, RestartSec=, WatchdogSec= (0: none), Nice= and CPUWeight= (None:
    none), TimeoutAbortSec= and ExecStopPost= (the ``deepxpalm`` arguments it runs after any
    exit)."""

    unit: str
    restart: str
    restart_sec: float
    watchdog_sec: float
    nice: int | None = None
    cpu_weight: int | None = None
    timeout_abort_sec: float = 10.0
    stop_post: tuple[str, ...] = ()

    def restarts_after(self, returncode: int) -> bool:
        """Whether systemd starts the process again after it ended with ``returncode``."""
        if self.restart == "always":
            return True
        if self.restart != "on-failure":
            return False
        if returncode < 0:
            return -returncode not in _CLEAN_SIGNALS
        return returncode != 0


def _seconds(value: str) -> float:
    match = re.fullmatch(r"\s*([0-9.]+)\s*(ms|s|min)?\s*", value)
    if match is None:
        raise ValueError(f"cannot read the time span {value!r}")
    scale = {"ms": 1e-3, "s": 1.0, "min": 60.0, None: 1.0}[match.group(2)]
    return float(match.group(1)) * scale


def policy(unit: str, units_dir: Path = UNITS_DIR) -> RestartPolicy | None:
    """``deepxpalm-<unit>.service``'s policy; None when no unit ships for that process."""
    path = units_dir / f"deepxpalm-{unit}.service"
    if not path.exists():
        return None
    keys: dict[str, str] = {}
    for line in path.read_text().splitlines():
        key, sep, value = line.partition("=")
        if sep and not line.lstrip().startswith("#"):
            keys[key.strip()] = value.strip()
    return RestartPolicy(
        unit=path.name,
        restart=keys.get("Restart", "no"),
        restart_sec=_seconds(keys.get("RestartSec", "100ms")),
        watchdog_sec=_seconds(keys.get("WatchdogSec", "0")),
        nice=int(keys["Nice"]) if "Nice" in keys else None,
        cpu_weight=int(keys["CPUWeight"]) if "CPUWeight" in keys else None,
        timeout_abort_sec=_seconds(keys.get("TimeoutAbortSec", keys.get("TimeoutStopSec", "10"))),
        stop_post=_deepxpalm_args(keys.get("ExecStopPost", "")),
    )


def _deepxpalm_args(command: str) -> tuple[str, ...]:
    """The arguments of an installed ``.../bin/deepxpalm ...`` command line; () for none."""
    argv = shlex.split(command)
    if not argv:
        return ()
    if not argv[0].endswith("/deepxpalm"):
        raise ValueError(f"a unit runs {argv[0]!r}; only the deepxpalm command is understood")
    return tuple(argv[1:])


def unit_nice(unit: str | None) -> int | None:
    """``Nice=`` of ``deepxpalm-<unit>.service``; None without a unit or a setting."""
    found = policy(unit) if unit else None
    return None if found is None else found.nice


def set_niceness(nice: int | None) -> None:
    """In a child before exec: run at ``nice``, as systemd runs the unit.

    The nodes' units ask for a higher priority than other work (the robot
    and operator nodes ``Nice=-10``): on a busy machine their loops keep
    their rate. Where the process may not raise its priority (not root, no
    CAP_SYS_NICE) it keeps the one it has: the same programs, less margin.
    ``None`` (no unit, or no setting): the parent's priority. Either way a
    child that leads a session of its own (the demo's) keeps its parent's
    session's scheduling weight (:func:`keep_parents_group_weight`).
    """
    if nice is not None:
        with contextlib.suppress(OSError):
            os.nice(nice - os.nice(0))
    if os.getsid(0) == os.getpid():
        keep_parents_group_weight()


def keep_parents_group_weight() -> None:
    """In a child that leads a session of its own: its parent's session's scheduling weight.

    Where the kernel groups processes by session before it weighs their
    priorities (``sched_autogroup``, the default on most desktops), a new
    session is a new group at nice 0, whatever the session it came from.
    The demo's children lead sessions only so that Ctrl-C reaches the demo
    alone; they keep the weight of the one they were started from.
    """
    share_group_weight(os.getppid(), os.getpid())


def share_group_weight(source_pid: int, target_pid: int) -> None:
    """The scheduling group of ``target_pid``'s session at the weight of ``source_pid``'s.

    Nothing where the kernel has no such groups or this process may not raise the weight.
    """
    with contextlib.suppress(OSError, ValueError, IndexError):
        weight = Path(f"/proc/{source_pid}/autogroup").read_text().split()[-1]
        Path(f"/proc/{target_pid}/autogroup").write_text(str(int(weight)))
