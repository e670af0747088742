"""A recorded demo session, exported, loaded back by LeRobot's own LeRobotDataset.

Every value LeRobot returns is checked against the MCAP file: frames and
stimuli to float32 equality, each row holding the newest record at or
before its time, the held frame within one sample period of the row.
"""

from __future__ import annotations

import bisect
import importlib.util
import json
import subprocess
import sys

import numpy as np
import pytest
from tests_support import why_the_demo_failed

from common.recording.mcap_recorder import read_recording
from deploy.export.cli import export
from deploy.export.resample import ExportConfig

FPS = 30
#: how long after the first robot frame every exported channel has its first record (the
#: camera last): 1.0 s measured beside two busy loops
CHANNELS_START_WITHIN_S = 2.0
# slow, but no check here is a timing: it may run beside other tests (make test's first lane)
pytestmark = [pytest.mark.slow, pytest.mark.untimed]


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """`deepxpalm demo --record`: both nodes, the simulated devices, 6 s."""
    out = tmp_path_factory.mktemp("session")
    proc = subprocess.run(
        [sys.executable, "-m", "deploy.cli", "demo", "--duration", "6", "--json", "--record", out],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, why_the_demo_failed(proc)  # its summary names what went wrong
    return out


@pytest.fixture(scope="module")
def records(session):
    out: dict[str, list] = {}
    for channel, t_ns, record in sorted(read_recording(session / "robot.mcap"), key=lambda r: r[1]):
        out.setdefault(channel, []).append((t_ns, record))
    return out


def _loaded(lerobot, session, tmp_path, episodes: str):
    root = tmp_path / f"ds-{episodes}"
    summary = export([session], root, ExportConfig(fps=FPS, episodes=episodes))
    npz = tmp_path / f"loaded-{episodes}.npz"
    lerobot.load(root, npz)
    with np.load(npz) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(arrays.pop("_meta").tobytes())
    return summary, arrays, meta, root


@pytest.fixture(scope="module")
def one_episode(lerobot, session, tmp_path_factory):
    """The session exported as one episode and loaded by LeRobot, once for the tests reading it."""
    return _loaded(lerobot, session, tmp_path_factory.mktemp("one-episode"), "session")


def _held(channel_records, t_row, before_first=None):
    """The newest record at or before ``t_row``; ``before_first`` if there is none yet."""
    times = [t for t, _ in channel_records]
    i = bisect.bisect_right(times, t_row) - 1
    if i < 0 and before_first is not None:
        return None, before_first
    assert i >= 0, "a row before the channel's first record"
    return channel_records[i]


#: a row before the robot's first stimulus (a grasp from the session's start, on a slow
#: machine) holds no stimulus: zeros, no pattern (docs/datasets.md)
NO_STIMULUS = {
    "decoded": {"stimulus": np.zeros((3, 3), np.float32), "pattern": None, "confidence": None}
}


def test_every_value_lerobot_loads_matches_the_recording(lerobot, session, records, tmp_path):
    summary, a, meta, _ = _loaded(lerobot, session, tmp_path, "grasp")
    assert meta["num_frames"] == summary["frames"] == len(a["index"]) > 60
    assert meta["num_episodes"] == summary["episodes"] >= 2
    assert meta["fps"] == FPS
    assert set(meta["tasks"]) == {"grasp the pipette"}
    assert "observation.tactile.frames" in meta["stats_keys"]
    np.testing.assert_array_equal(a["index"], np.arange(len(a["index"])))
    np.testing.assert_array_equal(a["timestamp"], (a["frame_index"] / FPS).astype(np.float32))
    period_ns = 1e9 / FPS
    ages = []
    for ep in meta["episodes"]:
        rows = range(ep["dataset_from_index"], ep["dataset_to_index"])
        assert ep["length"] == len(rows) and ep["deepxpalm/session"] == session.name
        assert a["observation.tactile.frames"][list(rows)].max() >= 0.3  # a grasp has contact
        for j, i in enumerate(rows):
            assert a["episode_index"][i] == ep["episode_index"] and a["frame_index"][i] == j
            t_row = ep["deepxpalm/t_first_ns"] + round(j * period_ns)
            t_f, frame = _held(records["robot/frame"], t_row)
            np.testing.assert_array_equal(a["observation.tactile.frames"][i], frame["frame"])
            assert a["observation.tactile.frame_seq"][i] == frame["frame_seq"]
            ages.append(t_row - t_f)
            assert a["observation.tactile.age"][i] == pytest.approx((t_row - t_f) / 1e9, abs=2e-6)
            stim = _held(records["robot/stimulus"], t_row, NO_STIMULUS)[1]["decoded"]
            np.testing.assert_array_equal(a["observation.stimulus"][i], stim["stimulus"])
            assert a["observation.perception.pattern"][i] == (
                -1 if stim["pattern"] is None else stim["pattern"]
            )
            assert a["observation.perception.confidence"][i] == np.float32(
                stim["confidence"] or 0.0
            )
            arm = _held(records["robot/arm"], t_row)[1]
            np.testing.assert_array_equal(
                a["observation.arm.joints"][i], arm["joints"].astype(np.float32)
            )
            grip = _held(records["robot/gripper"], t_row)[1]
            np.testing.assert_array_equal(
                a["observation.state"][i],
                np.append(arm["tcp_pose"], grip["position"]).astype(np.float32),
            )
            assert a["observation.gripper.object_status"][i] == grip["object_status"]
            # no operator commands in the demo: the arm holds still, the target stays the first
            assert not a["action"][i][:6].any()
            assert a["action"][i][6] == records["robot/gripper"][0][1]["requested_position"]
    ages = np.array(ages)
    assert (ages >= 0).all()
    # each row holds the newest frame recorded at or before its time (checked row by row
    # above), so a row's frame is older than a period only inside a gap of the recording
    # itself (the robot stalled: a loaded machine), and never older than its longest gap
    t_frames = np.array([t for t, _ in records["robot/frame"]], dtype=np.int64)
    gaps = np.diff(t_frames)
    assert ages.max() < max(gaps.max(), period_ns), (
        f"a row's frame is {ages.max() / 1e6:.0f} ms old, longer than the recording's "
        f"longest gap ({gaps.max() / 1e6:.0f} ms)"
    )


def test_the_camera_lerobot_decodes_is_the_rows_picture(session, records, one_episode):
    """The demo records its camera (the stamped test pattern) beside the robot; each row's
    picture, as LeRobot's loader decodes it from the video, is the newest camera frame at or
    before the row's time, and so within one camera period of the row's tactile frame."""
    from robot_side.camera.stamp import MS_MODULO, read_stamp

    summary, a, meta, _ = one_episode
    key = "observation.images.test_pattern"
    assert key in summary["features"] and meta["video_keys"] == [key]
    assert meta["features"][key]["info"]["video.codec"] == "h264"
    camera = [(t, r) for _, t, r in read_recording(session / "camera.mcap")]
    by_ms = {r["capture_wall_ns"] // 1_000_000 % MS_MODULO: t for t, r in camera}
    times = [t for t, _ in camera]
    period_ns = 1e9 / float(camera_fps(session))
    images = a[key]
    assert images.shape == (len(a["index"]), 3, 240, 320) and images.dtype == np.uint8
    t_first = meta["episodes"][0]["deepxpalm/t_first_ns"]
    frame_times = [t for t, _ in records["robot/frame"]]
    apart, stands_for, held_for = [], [], []
    for i, picture in enumerate(images):
        stamp = read_stamp(picture.transpose(1, 2, 0))
        assert stamp is not None, f"row {i}: the decoded picture's stamp is unreadable"
        t_row = t_first + round(i * 1e9 / FPS)
        t_held, _ = _held(camera, t_row)
        assert by_ms.get(stamp[0]) == t_held, f"row {i} shows another picture than it holds"
        t_tactile, _ = _held(records["robot/frame"], t_row)
        apart.append(abs(t_held - t_tactile))
        j = times.index(t_held)  # the picture stands until the next one (one period, or a stall)
        picture_stood = times[j + 1] - t_held if j + 1 < len(times) else period_ns
        k = bisect.bisect_left(frame_times, t_tactile)  # and the tactile frame until its next
        frame_stood = frame_times[k + 1] - t_tactile if k + 1 < len(frame_times) else 0
        stands_for.append(picture_stood)
        held_for.append(max(picture_stood, frame_stood))
    apart, stands_for = np.array(apart), np.array(stands_for)
    # one period of the recorded pictures: 100 ms at 10 fps; from the demo's 15 fps camera the
    # nearest frames to the 100 ms ticks are 67 or 133 ms apart. Both are the newest at or
    # before the row, so they are apart by less than the longer of the two stood: a stall of
    # either stream (a loaded machine) holds its record longer, and the row is judged by it
    bound = np.maximum(np.array(held_for), period_ns)
    assert (apart <= bound).all(), (
        f"{(apart > bound).sum()} rows' picture is further from their tactile frame than one "
        f"camera period: up to {(apart - bound).max() / 1e6:.0f} ms beyond"
    )
    stalled = stands_for > 1.5 * period_ns
    assert stalled.mean() < 0.5, f"the camera stalled for {stalled.mean():.0%} of the rows (load?)"


def camera_fps(session) -> str:
    from common.recording.mcap_recorder import read_metadata

    return read_metadata(session / "camera.mcap")["deepxpalm.camera"]["record_fps"]


def test_lerobot_policies_find_the_state_and_the_action(lerobot, one_episode):
    """LeRobot's own dataset_to_policy_features, ACTConfig and DiffusionConfig on an export.

    Both policies need an image or an environment state beside the robot
    state; the camera feature is what gives them one. The demo records its
    camera (the test pattern) when the video extra is installed, and both
    accept the export as it is; without a camera they must refuse for that
    reason alone: with a camera's feature added, the same features pass.
    """
    report = lerobot.policy_features(one_episode[3])  # the session exported as one episode
    features = report["features"]
    assert features["observation.state"] == ["STATE", [7]]
    assert features["action"] == ["ACTION", [7]]
    assert features["observation.tactile.frames"] == ["STATE", [2, 10, 10]]
    assert report["state_names"][:3] == ["ee.x", "ee.y", "ee.z"]
    assert report["state_names"][-1] == "gripper.pos"
    has_camera = any(k.startswith("observation.images.") for k in features)
    # the demo records its camera whenever the video extra is installed: then the export has it
    assert has_camera == (importlib.util.find_spec("aiortc") is not None), features
    for name, policy in report["policies"].items():
        assert policy["robot_state"] == [7] and policy["action"] == [7], name
        if has_camera:
            assert policy["accepted"] is True, (name, policy)
        else:
            assert not policy["accepted"] and "at least one image" in policy["refusal"], name
        assert policy["accepted_with_a_camera"] is True, (name, policy)


def test_one_episode_per_session_covers_the_recording(records, one_episode):
    _, a, meta, _ = one_episode
    assert meta["num_episodes"] == 1
    frames = records["robot/frame"]
    span_s = (frames[-1][0] - frames[0][0]) / 1e9
    # the whole session at the chosen rate: rows until the last tactile frame (the arm's
    # and the gripper's records go on a moment after it, while the node shuts its devices
    # down: no row holds a frame nobody knows still held), never beyond, and rows from the
    # moment every exported channel has a record (docs/datasets.md), which the camera's video
    # server, started beside the robot node, reaches a second or so later on a loaded machine
    rows = len(a["index"])
    assert rows <= span_s * FPS + 1, (rows, span_s)
    assert rows >= (span_s - CHANNELS_START_WITHIN_S) * FPS, (rows, span_s)
    truth = a["annotation.sim_truth_pattern"]
    assert set(np.unique(truth[truth >= 0])) <= set(range(12)) and (truth >= 0).any()


def test_train_reads_an_exported_dataset(session, tmp_path):
    from robot_side.perception import dataset as ds

    root = tmp_path / "ds"
    export([session], root, ExportConfig(fps=FPS))
    data = ds.load(root)
    assert len(data) > 20 and data.frames.dtype == np.float32
    assert set(np.unique(data.pattern)) <= set(range(12))
    assert data.meta["labels"] == "annotation.sim_truth_pattern"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "deploy.cli",
            "train",
            "--data",
            str(root),
            "--init",
            "default",
            "--epochs",
            "1",
            "--no-robustness",
            "--no-progress",
            "--out",
            str(tmp_path / "model"),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert f"loaded {len(data)} frames" in proc.stdout
    assert (tmp_path / "model" / "model.onnx").is_file()
