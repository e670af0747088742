"""Which episodes a dataset keeps, their task strings and their success.

Three sources, applied in this order (docs/datasets.md):

- the operator's marks, recorded while recording (``operator/episode_mark``):
  a mark counts for the episode in progress at its time or, between
  episodes, the one that ended last; the latest mark on an episode wins.
  ``discard`` leaves the episode out, ``failed`` keeps it with success
  false (or leaves it out with ``drop_failed``), ``success`` confirms it;
  a mark's task string is the episode's task;
- ``exclude``: episode numbers to leave out, as an export of the same
  recordings without ``exclude`` numbers them (what the user looked at);
- ``task_file``: a TOML file ``NUMBER = "task"``, in the same numbering,
  over the marks' tasks and the default ``task``.

An unmarked episode counts as a success: the operator marks what failed.
"""

from __future__ import annotations

import tomllib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from common.errors import ConfigError
from common.recording.episode_marks import DISCARD, FAILED, MAX_TASK_CHARS, Mark

Row = dict[str, Any]
#: the per-row column of LeRobot's convention: true on the last row of an episode that
#: reached its goal (its gym environments' ``next.success``)
SUCCESS = "next.success"


def load_task_file(path: Path) -> dict[int, str]:
    """``NUMBER = "task"`` lines (TOML) -> {number: task}; errors name the file and the line."""
    try:
        data = tomllib.loads(Path(path).read_text())
    except FileNotFoundError:
        raise ConfigError(f"task file {path} does not exist") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"task file {path} is not valid TOML: {e}") from None
    out: dict[int, str] = {}
    for key, task in data.items():
        if not key.isdigit():
            raise ConfigError(
                f'task file {path}: {key!r} is not an episode number (write 3 = "task")'
            )
        if not isinstance(task, str) or not task.strip() or len(task) > MAX_TASK_CHARS:
            raise ConfigError(
                f"task file {path}: episode {key}'s task must be a non-empty string of at most "
                f"{MAX_TASK_CHARS} characters"
            )
        out[int(key)] = task.strip()
    return out


@dataclass
class Verdict:
    """What the marks say of one episode: the latest kind, the latest task, all kinds."""

    kind: str | None = None
    task: str | None = None
    kinds: list[str] = field(default_factory=list)


def verdicts(marks: list[Mark], starts: list[int]) -> tuple[list[Verdict], int]:
    """One verdict per episode (``starts``: each one's first row time, in order).

    A mark counts for the last episode begun at or before it. Returns the
    verdicts and how many marks came before the session's first episode.
    """
    out = [Verdict() for _ in starts]
    early = 0
    i = -1
    for mark in marks:  # both in time order
        while i + 1 < len(starts) and starts[i + 1] <= mark.t_robot_ns:
            i += 1
        if i < 0:
            early += 1
            continue
        v = out[i]
        v.kind = mark.kind
        v.kinds.append(mark.kind)
        if mark.task is not None:
            v.task = mark.task
    return out, early


class Curator:
    """Sits between the episode cutter and the writer: drops, numbers, labels episodes.

    ``session(verdicts)`` starts a session (None: no marks); then the
    cutter's ``begin``, ``add`` and ``end`` calls pass through. The last row
    of each kept episode is held back one call, so its ``next.success`` is
    set before it is written.
    """

    def __init__(
        self,
        *,
        default_task: str,
        exclude: list[int],
        tasks: dict[int, str],
        drop_failed: bool,
        begin: Callable[[str, dict[str, Any]], None],
        add: Callable[[Row], None],
        end: Callable[[], None],
    ) -> None:
        self.default_task = default_task
        self.exclude = set(exclude)
        self.tasks = tasks
        self.drop_failed = drop_failed
        self._begin, self._add, self._end = begin, add, end
        self.number = 0  # the next episode's number, as an export without exclude gives it
        self.left_out: list[dict[str, Any]] = []
        self.failed: list[int] = []  # dataset episode indices kept with success false
        self.kept = 0
        self._verdicts: list[Verdict] | None = None
        self._k = 0  # episode of the session
        self._skip: dict[str, Any] | None = None  # the episode being left out
        self._held: Row | None = None
        self._success = True
        self._session = ""

    def session(self, name: str, session_verdicts: list[Verdict] | None) -> None:
        self._session = name
        self._verdicts = session_verdicts
        self._k = 0

    def begin(self) -> None:
        v = self._verdicts[self._k] if self._verdicts is not None else Verdict()
        self._k += 1
        self._held = None
        if v.kind == DISCARD or (v.kind == FAILED and self.drop_failed):
            self._skip = {"session": self._session, "reason": v.kind, "number": None}
            return
        number = self.number
        self.number += 1
        if number in self.exclude:
            self._skip = {"session": self._session, "reason": "exclude", "number": number}
            return
        self._skip = None
        self._success = v.kind != FAILED
        if not self._success:
            self.failed.append(self.kept)
        task = self.tasks.get(number) or v.task or self.default_task
        self._begin(
            task,
            {
                "deepxpalm/number": number,
                "deepxpalm/success": self._success,
                "deepxpalm/marks": ",".join(v.kinds),
            },
        )
        self.kept += 1

    def add(self, row: Row) -> None:
        if self._skip is not None:
            if "t_first_ns" not in self._skip:
                self._skip["t_first_ns"] = row["t_ns"]
            self._skip["rows"] = self._skip.get("rows", 0) + 1
            return
        if self._held is not None:
            self._add(self._held)
        row[SUCCESS] = False
        self._held = row

    def end(self) -> None:
        if self._skip is not None:
            self.left_out.append(self._skip)
            self._skip = None
            return
        if self._held is not None:
            self._held[SUCCESS] = self._success
            self._add(self._held)
            self._held = None
        self._end()

    def unused(self) -> dict[str, list[int]]:
        """Numbers given in exclude or the task file that no episode had."""
        return {
            "exclude": sorted(n for n in self.exclude if n >= self.number),
            "task_file": sorted(n for n in self.tasks if n >= self.number),
        }
