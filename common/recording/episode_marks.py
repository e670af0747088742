"""Episode marks: the operator's word on the episode being recorded.

While recording, the operator can say of the episode in progress (or the one
that just ended) that it failed, that it should be discarded, or that it
succeeded, optionally with the task it showed. The dashboard sends the mark
to the operator node, which records it on its own channel
(``operator/episode_mark``, on the operator's clock, like every record of
``operator.mcap``); ``deepxpalm export`` places each mark on the robot's
clock and applies it to the episode it falls in (docs/datasets.md).
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass
from pathlib import Path

#: the recording channel of a mark: {"kind": ..., "task": ... (optional), "source": ...}
CHANNEL = "operator/episode_mark"
FAILED, DISCARD, SUCCESS = "failed", "discard", "success"
KINDS = (FAILED, DISCARD, SUCCESS)
#: a task string longer than this is refused (LeRobot keeps one string per task)
MAX_TASK_CHARS = 200


def check_mark(kind: object, task: object = None) -> str | None:
    """Why a mark cannot be recorded (a sentence for the operator), or None when it can."""
    if kind not in KINDS:
        return f"kind must be one of {', '.join(KINDS)}, not {kind!r}"
    if task is None:
        return None
    if not isinstance(task, str) or not task.strip():
        return "task must be a non-empty string (or left out)"
    if len(task) > MAX_TASK_CHARS:
        return f"task must be at most {MAX_TASK_CHARS} characters"
    if any(not ch.isprintable() for ch in task):
        return "task must be one line of printable characters"
    return None


@dataclass(frozen=True)
class Mark:
    t_robot_ns: int  # on the robot's clock: where the export's rows are
    kind: str
    task: str | None
    t_operator_ns: int  # as recorded, on the operator's clock


def read_marks(path: Path) -> tuple[list[Mark], int]:
    """The marks of an operator recording on the robot's clock, in time order.

    Each mark's time is moved by the clock offset (robot minus operator) the
    node recorded nearest before it on ``operator/link`` (the first one after
    it when none came before). Returns the marks and how many could not be
    placed because the recording holds no clock offset at all (the node never
    heard the robot).
    """
    from common.recording.mcap_recorder import RecordingReader

    raw: list[tuple[int, str, str | None]] = []
    offsets: list[tuple[int, int]] = []
    for channel, t_ns, record in RecordingReader(path):
        if channel == CHANNEL:
            kind, task = record.get("kind"), record.get("task")
            if check_mark(kind, task) is None:
                raw.append((t_ns, kind, task))
        elif channel == "operator/link" and record.get("clock_offset_ns") is not None:
            offsets.append((t_ns, int(record["clock_offset_ns"])))
    if not raw:
        return [], 0
    if not offsets:
        return [], len(raw)
    offsets.sort()
    times = [t for t, _ in offsets]
    marks = []
    for t_ns, kind, task in raw:
        i = max(bisect.bisect_right(times, t_ns) - 1, 0)
        marks.append(Mark(t_ns + offsets[i][1], kind, task, t_ns))
    marks.sort(key=lambda m: m.t_robot_ns)
    return marks, 0
