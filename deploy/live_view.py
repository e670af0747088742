"""The demo's live terminal view: both pads, the pattern, the stimulus, the servos, the link.

The operator node runs as a process of its own; what the view shows is its
status file (``deepxpalm operator --status-file``), read by ``OperatorStatus``.
"""

from __future__ import annotations

import contextlib
import json
import math
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from common.tactile.contract import SATURATION_N, pattern_name
from operator_side.dashboard.snapshot import Snapshot

_SHADES = " .:-=+*#%@"
_RESET = "\x1b[0m"


class OperatorStatus:
    """An operator node's status file, as another process reads it: its snapshot, counters
    and latency sample count (the file is replaced whole, never half written; a restarted
    node's first write replaces its predecessor's last). When the node is up, and where
    its dashboard is, its READY=1 says (``deploy.units``)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._last: dict[str, Any] | None = None

    def read(self) -> dict[str, Any] | None:
        """The newest status; the last one read while none is there (None before the first)."""
        with contextlib.suppress(FileNotFoundError, ValueError):
            self._last = json.loads(self.path.read_text())
        return self._last

    def snapshot(self) -> Snapshot | None:
        status = self.read()
        return None if status is None else Snapshot.from_json(status["snapshot"])

    def stats(self) -> dict[str, float]:
        status = self.read()
        return {} if status is None else dict(status["snapshot"]["stats"])

    def latency_samples(self) -> int:
        status = self.read()
        return 0 if status is None else int(status["latency_samples"])


def _heat(v: float, vmax: float = SATURATION_N) -> str:
    """Two characters on a 256-colour background ramp, from dark blue to yellow."""
    t = min(max(v / vmax, 0.0), 1.0)
    ramp = (17, 18, 19, 25, 31, 37, 71, 107, 143, 179, 215, 221, 227)
    shade = _SHADES[round(t * (len(_SHADES) - 1))]
    return f"\x1b[48;5;{ramp[round(t * (len(ramp) - 1))]}m{shade}{shade}"


def _pads(frame: np.ndarray | None) -> list[str]:
    if frame is None:
        return ["(no frame yet)"] + [""] * 10
    lines = ["finger 1              finger 2"]
    for r in range(10):
        left = "".join(_heat(float(v)) for v in frame[0, r]) + _RESET
        right = "".join(_heat(float(v)) for v in frame[1, r]) + _RESET
        lines.append(f"{left}  {right}")
    return lines


def _stimulus(stim: np.ndarray | None) -> list[str]:
    lines = ["stimulus (N)"]
    for r in range(3):
        if stim is None:
            lines.append("  -     -     -")
        else:
            lines.append(" ".join(f"{v:5.2f}" if v > 0 else "  .  " for v in stim[r]))
    return lines


def _ms(v: float | None) -> str:
    return "  -  " if v is None else f"{v:6.2f}"


def render(snap: Snapshot, scene_name: str, elapsed_s: float) -> str:
    s, r = snap.stats, snap.robot_stats
    pattern = (
        "none" if snap.pattern is None else f"{snap.pattern:2d} ({pattern_name(snap.pattern)})"
    )
    conf = "" if snap.confidence is None else f"  p={snap.confidence:.2f}"
    state_colour = {"ok": 42, "stale": 43, "down": 41}.get(snap.link_state, 45)
    lines = [
        f"DeepXPalm demo - scene {scene_name} - {elapsed_s:5.1f} s   "
        f"link \x1b[{state_colour}m {snap.link_state.upper()} {_RESET}"
        + ("" if snap.age_ms is None else f"  age {snap.age_ms:5.1f} ms"),
        "",
        *_pads(snap.frame),
        "",
        f"pattern {pattern}{conf}   grip level {snap.grip_level or '-'}",
        *_stimulus(snap.stimulus),
        "",
        "servo angles (deg) "
        + "  ".join(
            f"L{n} {math.degrees(a):6.1f} {math.degrees(e):6.1f}"
            for n, (a, e) in enumerate(snap.goal_angles)
        ),
        "latency capture->servo  p50 {} ms  p99 {} ms  max {} ms".format(
            *(_ms(s.get(k)) for k in ("latency_p50_ms", "latency_p99_ms", "latency_max_ms"))
        ),
        "robot: frames {}  no-contact {}  inferences {}  published {}".format(
            *(
                int(r.get(k, 0))
                for k in ("frames_captured", "frames_no_contact", "inferences", "stimuli_published")
            )
        ),
        "operator: received {}  servo writes {}  lift-offs {}  rejected {}".format(
            *(
                int(s.get(k, 0))
                for k in ("stimuli_received", "servo_writes", "lift_offs", "decode_errors")
            )
        ),
        _latch_line(r),
        "keys: o open  c close  1-9 grip level  w/a/s/d/r/f jog arm  q/e turn wrist  space STOP"
        "  g resume   Ctrl-C quit",
    ]
    return "\x1b[H\x1b[2J" + "\n".join(lines) + "\n"


def _latch_line(robot_stats: dict[str, float]) -> str:
    """The robot's stop latch, as every operator sees it (its heartbeat)."""
    if robot_stats.get("arm_stop_latched"):
        return "arm \x1b[41m STOPPED \x1b[0m latched on the robot: jogs refused until g (resume)"
    return "arm free to jog (space: STOP, latched on the robot until g)"


class Keyboard:
    """Single keys from a terminal without Enter (cbreak), restored on exit.

    o / c: open the gripper / close it to the current grip level; 1-9: grip
    level 3..27; w a s d r f: jog the arm +X -Y -X +Y +Z -Z (held keys repeat,
    which keeps the jog alive); q / e: turn the wrist about the base X axis
    (the fingers' closing axis at the UR's home pose, so the pipette's tilt on
    the pads changes); space: STOP the arm (latched on the robot: every jog,
    from here or a dashboard, is refused until a resume); g: resume.
    """

    JOG_M_S = 0.02
    TURN_RAD_S = 0.3
    _TURNS: ClassVar[dict[str, int]] = {"q": 1, "e": -1}
    _JOGS: ClassVar[dict[str, tuple[int, int, int]]] = {
        "w": (1, 0, 0), "s": (-1, 0, 0), "a": (0, -1, 0), "d": (0, 1, 0),
        "r": (0, 0, 1), "f": (0, 0, -1),
    }  # fmt: skip

    def __init__(self) -> None:
        import sys

        self._stdin = sys.stdin
        self._saved = None
        self.grip_level = 16

    def __enter__(self) -> Keyboard:
        import termios
        import tty

        if self._stdin.isatty():
            self._saved = termios.tcgetattr(self._stdin)
            tty.setcbreak(self._stdin)
        return self

    def __exit__(self, *exc: object) -> None:
        import termios

        if self._saved is not None:
            termios.tcsetattr(self._stdin, termios.TCSADRAIN, self._saved)

    def commands(self) -> list[tuple[str, dict]]:
        """Keys typed since the last call, as (action, arguments) for send_command."""
        import os
        import select

        if self._saved is None:
            return []
        out: list[tuple[str, dict]] = []
        while select.select([self._stdin], [], [], 0)[0]:
            key = os.read(self._stdin.fileno(), 1).decode(errors="ignore").lower()
            if key == "o":
                out.append(("gripper_open", {}))
            elif key == "c":
                out.append(("gripper_close", {"grip_level": self.grip_level}))
            elif key.isdigit() and key != "0":
                self.grip_level = 3 * int(key)
                out.append(("gripper_close", {"grip_level": self.grip_level}))
            elif key in self._JOGS:
                v = (*(self.JOG_M_S * c for c in self._JOGS[key]), 0.0, 0.0, 0.0)
                out.append(("arm_jog", {"velocity": v}))
            elif key in self._TURNS:
                v = (0.0, 0.0, 0.0, self.TURN_RAD_S * self._TURNS[key], 0.0, 0.0)
                out.append(("arm_jog", {"velocity": v}))
            elif key == " ":
                out.append(("arm_stop", {}))
            elif key == "g":
                out.append(("arm_resume", {}))
        return out


def dashboard_line(url: str, url_file: object) -> str:
    """The dashboard's line under every frame: its address without the token (the frames
    go wherever the terminal's output goes: a screen share, a log of the session), and the
    0600 file holding the address with it."""
    from common.web.web_token import without_token

    return f"dashboard {without_token(url)}  (with its token: {url_file})\n"
