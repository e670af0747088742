"""Which episode a mark counts for, and what export does with it, on recordings of known shape.

A robot recording with a grasp every 3 s (2 s of contact) and an operator
recording with a clock offset of 5 ms and the marks a test gives, written
the way the nodes write them; the export's own files are read back.
"""

from __future__ import annotations

import shutil

import numpy as np
import pyarrow.parquet as pq
import pytest
from synthetic import POSE, ROBOT_CONFIG, _gripper

from common.errors import ConfigError
from common.recording.mcap_recorder import McapRecorder
from deploy.export.cli import export
from deploy.export.resample import ExportConfig

#: each export is well under a second, but the first in a process imports the exporter's
#: libraries (several seconds); nothing here is a timing
pytestmark = [pytest.mark.slow, pytest.mark.untimed]

MS = 1_000_000
T0 = 10_000 * MS
OFFSET = 5 * MS  # robot clock minus operator clock
SECONDS = 12  # grasps from 0.5 s to 2 s, 3 s to 5 s, 6 s to 8 s, 9 s to 11 s


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    path = tmp_path_factory.mktemp("robot") / "robot.mcap"
    meta = {"deepxpalm.node": {"node": "robot", "config_toml": ROBOT_CONFIG}}
    with McapRecorder(path, flush_interval_s=3600, fsync=False, metadata=meta) as rec:
        for step in range(SECONDS * 100):
            t, s = T0 + step * 10 * MS, step / 100
            contact = s % 3.0 < 2.0 and s > 0.5
            if step % 3 == 0:
                frame = np.full((2, 10, 10), 1.0 if contact else 0.0, np.float32)
                rec.write("robot/frame", t, {"frame": frame, "frame_seq": step, "t_capture_ns": t})
            if step % 5 == 0:
                rec.write("robot/arm", t, {"tcp_pose": np.array(POSE), "joints": np.zeros(6)})
                rec.write("robot/gripper", t, _gripper(t))
    return path


def session(tmp_path, robot, marks, offsets=True):
    """A session folder: the robot's file and an operator's marking at robot times ``marks``."""
    folder = tmp_path / "session"
    folder.mkdir()
    shutil.copy(robot, folder / "robot.mcap")
    meta = {"deepxpalm.node": {"node": "operator", "config_toml": "[operator]\n"}}
    path = folder / "operator.mcap"
    with McapRecorder(path, flush_interval_s=3600, fsync=False, metadata=meta) as rec:
        if offsets:
            for k in range(SECONDS * 10):
                rec.write("operator/link", T0 - OFFSET + k * 100 * MS, {"clock_offset_ns": OFFSET})
        for t_s, kind, *task in marks:
            record = {"kind": kind, "source": "test", **({"task": task[0]} if task else {})}
            rec.write("operator/episode_mark", T0 - OFFSET + round(t_s * 1e9), record)
    return folder


def exported(tmp_path, folder, **config):
    out = tmp_path / "ds"
    summary = export([folder], out, ExportConfig(**config))
    episodes = pq.read_table(out / "meta/episodes/chunk-000/file-000.parquet").to_pylist()
    data = pq.read_table(out / "data/chunk-000/file-000.parquet").to_pydict()
    return summary, episodes, data


def starts_s(episodes):
    return [round((e["deepxpalm/t_first_ns"] - T0) / 1e9, 2) for e in episodes]


def test_a_mark_counts_for_the_grasp_in_progress_or_the_last_one_and_the_latest_wins(
    tmp_path, robot
):
    marks = [
        (0.1, "failed"),  # before any grasp: counts for none
        (1.0, "failed", "slipped"),  # in grasp 0
        (2.6, "discard"),  # after grasp 0 ended, before grasp 1: grasp 0
        (2.7, "success"),  # ... and changed back: the latest mark wins, its task stays
        (4.0, "discard"),  # grasp 1 left out
        (8.5, "failed"),  # between grasps: grasp 2
    ]
    summary, episodes, data = exported(tmp_path, session(tmp_path, robot, marks))
    assert summary["marks"] == {"read": 6, "unplaced": 0, "before_first_episode": 1}
    assert starts_s(episodes) == [0.27, 5.73, 8.73]  # a 0.25 s margin before contact
    assert [e["deepxpalm/number"] for e in episodes] == [0, 1, 2]
    assert [e["deepxpalm/marks"] for e in episodes] == ["failed,discard,success", "failed", ""]
    assert [e["deepxpalm/success"] for e in episodes] == [True, False, True]
    assert [e["tasks"] for e in episodes] == [["slipped"], *[["grasp the pipette"]] * 2]
    assert summary["failed_episodes"] == [1]
    [left] = summary["left_out"]
    assert left["reason"] == "discard" and round((left["t_first_ns"] - T0) / 1e9, 2) == 2.73
    # next.success: the last row of each successful episode, nowhere else
    success = np.array(data["next.success"])
    ends = [e["dataset_to_index"] - 1 for e in episodes]
    assert np.flatnonzero(success).tolist() == [ends[0], ends[2]]


def test_exclude_and_task_file_number_episodes_as_an_export_without_exclude(tmp_path, robot):
    folder = session(tmp_path, robot, [(4.0, "discard"), (7.0, "failed")])
    tasks = tmp_path / "tasks.toml"
    tasks.write_text('0 = "first"\n2 = "third"\n')
    summary, episodes, _ = exported(tmp_path, folder, exclude=[1, 9], task_file=tasks)
    # numbers 0, 1, 2 are the grasps at 0.5, 6 and 9 s (the one at 3 s was discarded)
    assert starts_s(episodes) == [0.27, 8.73]
    assert [e["deepxpalm/number"] for e in episodes] == [0, 2]
    assert [e["tasks"] for e in episodes] == [["first"], ["third"]]
    assert [e["reason"] for e in summary["left_out"]] == ["discard", "exclude"]
    assert summary["unused_numbers"] == {"exclude": [9], "task_file": []}
    assert summary["failed_episodes"] == []


def test_drop_failed_leaves_failed_grasps_out(tmp_path, robot):
    folder = session(tmp_path, robot, [(1.0, "failed")])
    summary, episodes, _ = exported(tmp_path, folder, drop_failed=True)
    assert starts_s(episodes) == [2.73, 5.73, 8.73]
    assert all(e["deepxpalm/success"] for e in episodes)
    assert [e["reason"] for e in summary["left_out"]] == ["failed"]


def test_marks_without_a_clock_offset_are_reported_not_guessed(tmp_path, robot):
    folder = session(tmp_path, robot, [(1.0, "discard")], offsets=False)
    summary, episodes, _ = exported(tmp_path, folder)
    assert summary["marks"] == {"read": 1, "unplaced": 1, "before_first_episode": 0}
    assert len(episodes) == 4 and summary["left_out"] == []


def test_a_bad_task_file_is_named(tmp_path, robot):
    folder = session(tmp_path, robot, [])
    bad = tmp_path / "tasks.toml"
    bad.write_text('first = "grasp"\n')
    with pytest.raises(ConfigError, match="not an episode number"):
        export([folder], tmp_path / "ds", ExportConfig(task_file=bad))
    with pytest.raises(ConfigError, match="does not exist"):
        export([folder], tmp_path / "ds2", ExportConfig(task_file=tmp_path / "none.toml"))
