"""What the page is sent: a snapshot as small JSON, and the last minute of link health.

Kept apart from the server so the numbers the page shows can be tested
without a browser or a socket.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from common.config.typed import to_dict
from common.tactile.contract import MASKS, N_PATTERNS, pattern_name
from common.wire.messages import ARM_SAFETY_MODES, ASSIST_PHASES
from operator_side.dashboard.jog_config import JogConfig
from operator_side.dashboard.snapshot import Snapshot
from operator_side.palm.renderer import RendererConfig

# Fields whose change is worth a push; age and counters ride along with them
# or with the periodic refresh, or the page would be pushed at the full rate
# even while nothing it draws moves.
CONTENT_KEYS = (
    "link_state",
    "stimulus",
    "pattern",
    "confidence",
    "grip_level",
    "counts",
    "arm",
    "control",
)
STATS_SHOWN = (
    "stimuli_received",
    "servo_writes",
    "lift_offs",
    "decode_errors",
    "commands_sent",
    "latency_p50_ms",
    "latency_p99_ms",
)


def _round(a: np.ndarray | None, digits: int) -> Any:
    if a is None:
        return None
    return np.round(np.asarray(a, dtype=np.float64), digits).tolist()


def _finite(v: float | None, digits: int) -> float | None:
    if v is None or not math.isfinite(v):
        return None
    return round(float(v), digits)


def snapshot_view(snap: Snapshot) -> dict[str, Any]:
    """A snapshot as JSON-able data, rounded to what a screen can show.

    The frame (200 numbers, the bulk of a message) is under ``frame``; the
    caller leaves it out of a push when it has not changed.
    """
    return {
        "link_state": snap.link_state,
        "age_ms": _finite(snap.age_ms, 1),
        "stimulus": _round(snap.stimulus, 3),
        "pattern": snap.pattern,
        "pattern_name": None if snap.pattern is None else pattern_name(snap.pattern),
        "confidence": _finite(snap.confidence, 3),
        "grip_level": snap.grip_level,
        "frame": _round(snap.frame, 2),
        "angles": _round(snap.goal_angles, 5),
        "counts": [int(c) for c in np.asarray(snap.goal_counts).reshape(-1)],
        "stats": {k: _finite(snap.stats.get(k), 2) for k in STATS_SHOWN if k in snap.stats},
        "arm": arm_view(snap.robot_stats),
        "control": snap.control,
    }


POSE_KEYS = ("arm_x", "arm_y", "arm_z", "arm_rx", "arm_ry", "arm_rz")


def arm_view(robot_stats: dict[str, float]) -> dict[str, Any] | None:
    """The arm as the robot's latest heartbeat reported it; None when it reports no arm.

    Pose in millimetres and degrees (rotation vector), rounded to what a
    person reads; the workspace box and speed caps are the robot's own.
    """
    r = robot_stats
    if "arm_ws_min_x" not in r:
        return None
    pose = None
    if all(k in r for k in POSE_KEYS):
        pose = [round(r[k] * 1000, 1) for k in POSE_KEYS[:3]] + [
            round(math.degrees(r[k]), 1) for k in POSE_KEYS[3:]
        ]
    safety = r.get("arm_safety_mode")
    return {
        "pose": pose,
        "speed_mm_s": None if "arm_speed_m_s" not in r else round(r["arm_speed_m_s"] * 1000, 1),
        "angular_deg_s": None
        if "arm_angular_speed_rad_s" not in r
        else round(math.degrees(r["arm_angular_speed_rad_s"]), 1),
        "safety": None
        if safety is None
        else ARM_SAFETY_MODES.get(int(safety), f"mode {int(safety)}"),
        "program_running": None
        if "arm_program_running" not in r
        else bool(r["arm_program_running"]),
        "jogging": bool(r.get("arm_jogging", 0)),
        # an operator's STOP holds the arm on the robot: every page of every operator shows it
        "stop_latched": bool(r.get("arm_stop_latched", 0)),
        "deadman_stops": int(r.get("arm_deadman_stops", 0)),
        "link_deadman_trips": int(r.get("deadman_trips", 0)),
        # commands the robot refused as older than its max_command_age_ms (a RESUME among them
        # leaves the stop latched: the page says so, and a person presses RESUME again)
        "commands_stale": int(r.get("commands_stale", 0)),
        # the assist an operator holds: its phase, re-grasps, and commands it issued
        "assist": None
        if "assist_phase" not in r
        else {
            "phase": _name(ASSIST_PHASES, r["assist_phase"]),
            "regrasps": int(r.get("assist_regrasps", 0)),
            "steps": int(r.get("assist_steps", 0)),
        },
        "available": bool(r.get("arm_available", 1)),
        "workspace_mm": [
            [round(r[f"arm_ws_min_{a}"] * 1000, 1) for a in "xyz"],
            [round(r[f"arm_ws_max_{a}"] * 1000, 1) for a in "xyz"],
        ],
        "max_linear_mm_s": round(r.get("arm_max_linear_m_s", 0.0) * 1000, 1),
        "max_angular_deg_s": round(math.degrees(r.get("arm_max_angular_rad_s", 0.0)), 1),
    }


def hello_view(
    renderer: RendererConfig,
    stale_after_ms: float,
    max_rate_hz: float,
    jog: JogConfig | None = None,
) -> dict:
    """Sent once per connection: what the page needs to draw but never changes."""
    g, c = renderer.geometry, renderer.contact
    return {
        "jog": to_dict(jog or JogConfig()),
        "type": "hello",
        "geometry": {"l1": g.l1, "l2": g.l2, "l3": g.l3, "l4": g.l4, "l5": g.l5},
        "contact": {
            "column_x_mm": list(c.column_x_mm),
            "palm_y_mm": c.palm_y_mm,
            "max_depth_mm": c.max_depth_mm,
            "retract_point_mm": list(c.retract_point_mm),
        },
        "patterns": [
            {
                "id": p,
                "name": pattern_name(p),
                "cells": [[int(r), int(col)] for r, col in np.argwhere(MASKS[p])],
            }
            for p in range(N_PATTERNS)
        ],
        "stale_after_ms": stale_after_ms,
        "max_rate_hz": max_rate_hz,
        "history_s": HISTORY_S,
    }


HISTORY_S = 60


@dataclass
class _Bucket:
    t_s: float
    latency_ms: float | None = None
    sent: int = 0
    received: int = 0


@dataclass
class LinkHistory:
    """Latency and loss per second over the last minute, from snapshots alone.

    Latency: the youngest stimulus age seen in each second. Age is "now minus
    the capture time of the newest confirmed frame" (robot clock mapped to
    ours), so its minimum over a second is the capture-to-operator latency,
    overestimated by at most one sampling period.

    Loss: stimuli the robot says it sent (its heartbeat counters) against
    stimuli that arrived. Each robot count is paired with our count at the
    moment its heartbeat is first seen: both then cover the same stimuli
    (the heartbeat travelled behind them), so in-flight messages never read
    as lost. A restarted robot (counters going back) starts a new baseline.
    """

    window_s: int = HISTORY_S
    buckets: deque[_Bucket] = field(default_factory=deque)
    _robot_sent: int | None = None
    _pair: tuple[int, int] | None = None  # (robot sent, we received) at the last heartbeat

    def add(self, t_s: float, snap: Snapshot) -> bool:
        """Fold one snapshot in; True when a second was completed (history changed)."""
        second = math.floor(t_s)
        closed = False
        if not self.buckets or self.buckets[-1].t_s != second:
            closed = bool(self.buckets)
            self.buckets.append(_Bucket(second))
            while self.buckets and self.buckets[0].t_s <= second - self.window_s:
                self.buckets.popleft()
        b = self.buckets[-1]
        if snap.age_ms is not None and math.isfinite(snap.age_ms):
            b.latency_ms = snap.age_ms if b.latency_ms is None else min(b.latency_ms, snap.age_ms)
        self._count(b, snap)
        return closed

    def _count(self, b: _Bucket, snap: Snapshot) -> None:
        r = snap.robot_stats
        if "stimuli_published" not in r:
            return
        sent = int(r.get("stimuli_published", 0) + r.get("keyframes", 0))
        if sent == self._robot_sent:
            return  # no new robot heartbeat since the last sample
        self._robot_sent = sent
        received = int(
            snap.stats.get("stimuli_received", 0) + snap.stats.get("stimuli_out_of_order", 0)
        )
        last, self._pair = self._pair, (sent, received)
        if last is None or sent < last[0] or received < last[1]:
            return
        b.sent += sent - last[0]
        b.received += received - last[1]

    def lost_per_bucket(self) -> list[float]:
        """Messages lost in each second, with the pairing's noise settled.

        The running deficit (sent minus received) is the true cumulative loss
        plus a message or two that one pairing counted early and the next
        counts back. Loss never comes back, so the cumulative loss up to a
        second is the smallest deficit from then on; its steps are the
        losses. The newest second settles when the next one arrives.
        """
        deficit, running = [], 0
        for b in self.buckets:
            running += b.sent - b.received
            deficit.append(running)
        settled, low = [0.0] * len(deficit), math.inf
        for i in range(len(deficit) - 1, -1, -1):
            low = min(low, deficit[i])
            settled[i] = low
        out, prev = [], 0.0
        for value in settled:
            out.append(max(value - prev, 0.0))
            prev = max(prev, value)
        return out

    def view(self) -> dict[str, Any]:
        t = [b.t_s for b in self.buckets]
        lost = self.lost_per_bucket()
        loss = [
            None if b.sent == 0 else round(min(n / b.sent, 1.0), 4)
            for b, n in zip(self.buckets, lost, strict=True)
        ]
        sent = sum(b.sent for b in self.buckets)
        lat = [b.latency_ms for b in self.buckets if b.latency_ms is not None]
        return {
            "t_end_s": t[-1] if t else None,
            "t": [x - t[-1] for x in t] if t else [],
            "latency_ms": [_finite(b.latency_ms, 1) for b in self.buckets],
            "loss": loss,
            "summary": {
                "latency_median_ms": _finite(float(np.median(lat)), 1) if lat else None,
                "latency_max_ms": _finite(max(lat), 1) if lat else None,
                "loss": None if sent == 0 else round(min(sum(lost) / sent, 1.0), 4),
                "sent": sent,
                "lost": round(sum(lost)),
            },
        }


def _name(names: tuple[str, ...], code: float) -> str:
    i = int(code)
    return names[i] if 0 <= i < len(names) else f"phase {i}"
