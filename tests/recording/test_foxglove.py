"""Recordings Foxglove shows with no configuration: its message types, checked against its own.

The schemas the recorder writes are compared field by field with the
descriptors Foxglove publishes (the ``foxglove-schemas-protobuf`` package);
every Foxglove message of a recorded lab demo is validated against the
schema in the file (``jsonschema``) and parsed into Foxglove's protobuf
message, which refuses an unknown field or a wrong type. The same lab
recording is exported with its overview camera and loaded by LeRobot.
"""

from __future__ import annotations

import base64
import importlib
import json
import math
import os
import subprocess
import sys
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mcap", reason="recording needs the 'record' extra")
jsonschema = pytest.importorskip("jsonschema", reason="the 'dev' extra validates schemas")
pytest.importorskip("foxglove_schemas_protobuf", reason="Foxglove's schemas: the 'dev' extra")

from google.protobuf import json_format  # noqa: E402 (after the skips)
from google.protobuf.descriptor import FieldDescriptor  # noqa: E402
from mcap.reader import make_reader  # noqa: E402
from tests_support import why_the_demo_failed  # noqa: E402

from common.recording import foxglove  # noqa: E402
from common.recording.mcap_recorder import McapRecorder, read_recording  # noqa: E402
from common.rotation import quaternion_to_matrix, rotvec_to_matrix  # noqa: E402

REPO = Path(__file__).resolve().parents[2]


def _proto_class(type_name: str):
    short = type_name.split(".", 1)[1]
    module = importlib.import_module(f"foxglove_schemas_protobuf.{short}_pb2")
    return getattr(module, short)


_SCALARS = {
    FieldDescriptor.TYPE_DOUBLE: {"type": "number"},
    FieldDescriptor.TYPE_FLOAT: {"type": "number"},
    FieldDescriptor.TYPE_FIXED32: {"type": "integer", "minimum": 0},
    FieldDescriptor.TYPE_UINT32: {"type": "integer", "minimum": 0},
    FieldDescriptor.TYPE_STRING: {"type": "string"},
    FieldDescriptor.TYPE_BOOL: {"type": "boolean"},
    FieldDescriptor.TYPE_BYTES: {"type": "string", "contentEncoding": "base64"},
}


def _compare(schema: dict, descriptor, where: str) -> None:
    """Every field of Foxglove's message, and no other, with its JSON type."""
    assert schema["type"] == "object", where
    props = schema["properties"]
    assert set(props) == {f.name for f in descriptor.fields}, where
    for f in descriptor.fields:
        sub = props[f.name]
        at = f"{where}.{f.name}"
        repeated = f.is_repeated
        if repeated:
            assert sub["type"] == "array", at
            sub = sub["items"]
        if f.type == FieldDescriptor.TYPE_MESSAGE:
            full = f.message_type.full_name
            if full in ("google.protobuf.Timestamp", "google.protobuf.Duration"):
                assert set(sub["properties"]) == {"sec", "nsec"}, at
                assert sub["properties"]["nsec"]["maximum"] == 999_999_999, at
                if full.endswith("Timestamp"):
                    assert sub["properties"]["sec"]["minimum"] == 0, at
            else:
                assert sub["title"] == full, at
                _compare(sub, f.message_type, at)
        elif f.type == FieldDescriptor.TYPE_ENUM:
            values = {v.number: v.name for v in f.enum_type.values}
            assert {o["const"]: o["title"] for o in sub["oneOf"]} == values, at
        else:
            assert sub == _SCALARS[f.type], at


@pytest.mark.parametrize("type_name", sorted(foxglove.SCHEMAS))
def test_schemas_match_foxglove_published_ones(type_name):
    schema = foxglove.SCHEMAS[type_name]
    assert schema["title"] == type_name
    _compare(schema, _proto_class(type_name).DESCRIPTOR, type_name)


def _to_proto_json(value, descriptor):
    """Foxglove's JSON form ({sec, nsec} times) -> protobuf's JSON form, by the descriptor."""
    out = {}
    for key, v in value.items():
        f = descriptor.fields_by_name.get(key)
        if f is None or f.type != FieldDescriptor.TYPE_MESSAGE:
            out[key] = v
            continue
        full = f.message_type.full_name
        if full == "google.protobuf.Timestamp":
            out[key] = _rfc3339(v)
        elif full == "google.protobuf.Duration":
            out[key] = f"{v['sec'] + v['nsec'] / 1e9:.9f}s"
        elif f.is_repeated:
            out[key] = [_to_proto_json(x, f.message_type) for x in v]
        else:
            out[key] = _to_proto_json(v, f.message_type)
    return out


def _rfc3339(t: dict) -> str:
    import datetime

    whole = datetime.datetime.fromtimestamp(t["sec"], datetime.UTC)
    return whole.strftime("%Y-%m-%dT%H:%M:%S") + f".{t['nsec']:09d}Z"


#: one validator per schema, its schema checked once: ``jsonschema.validate`` checks the
#: schema against its metaschema at every call (14 of a lab recording's 16 s of checking)
_VALIDATORS: dict[str, jsonschema.protocols.Validator] = {}


def check_message(type_name: str, message: dict, schema: dict) -> object:
    """Valid by the file's JSON Schema and parsed, strictly, into Foxglove's protobuf message."""
    key = json.dumps(schema, sort_keys=True)
    validator = _VALIDATORS.get(key)
    if validator is None:
        cls = jsonschema.validators.validator_for(schema)
        cls.check_schema(schema)
        validator = _VALIDATORS[key] = cls(schema)
    validator.validate(message)
    cls = _proto_class(type_name)
    return json_format.ParseDict(_to_proto_json(message, cls.DESCRIPTOR), cls())


def test_conversions_by_hand():
    """A UR rotation vector becomes the quaternion of the same rotation; pads scale to 0..1."""
    pose = [0.1, -0.2, 0.3, 0.0, math.pi, 0.0]  # tool down: UR's usual pose, |r| = pi
    tf = foxglove.tcp_transform(pose, 1_700_000_000_123_456_789)
    assert tf["timestamp"] == {"sec": 1_700_000_000, "nsec": 123_456_789}
    q = tf["rotation"]
    m = quaternion_to_matrix(np.array([q["w"], q["x"], q["y"], q["z"]]))
    assert np.allclose(m, rotvec_to_matrix(np.array(pose[3:])), atol=1e-12)
    rng = np.random.default_rng(3)
    rv = rng.normal(size=3)
    q2 = foxglove.tcp_transform([0, 0, 0, *rv], 0)["rotation"]
    m2 = quaternion_to_matrix(np.array([q2["w"], q2["x"], q2["y"], q2["z"]]))
    assert np.allclose(m2, rotvec_to_matrix(rv), atol=1e-12)

    frame = np.zeros((2, 10, 10), np.float32)
    frame[0, 4, 5] = 4.5  # half of saturation
    frame[1, 0, 0] = 20.0  # beyond it: white
    left, right = foxglove.pad_images(frame, 0)
    px = np.frombuffer(base64.b64decode(left["data"]), "<f4").reshape(10, 10)
    assert px[4, 5] == pytest.approx(0.5) and px.sum() == pytest.approx(0.5)
    assert np.frombuffer(base64.b64decode(right["data"]), "<f4")[0] == 1.0

    open_, closed = foxglove.finger_transforms(0, 0), foxglove.finger_transforms(255, 0)
    assert open_[0]["translation"]["y"] == pytest.approx(0.0425)
    assert open_[1]["translation"]["y"] == pytest.approx(-0.0425)
    assert closed[0]["translation"]["y"] == 0.0


# ------------------------------------------------------------ the lab demo
@pytest.fixture(scope="module")
def lab_session(tmp_path_factory):
    """``deepxpalm demo --scene lab --record DIR``: the lab's camera, the arm, both nodes."""
    pytest.importorskip("mujoco", reason="the simulated lab needs the 'lab' extra (MuJoCo)")
    pytest.importorskip("aiortc", reason="the lab's camera is recorded by the 'video' extra")
    out = tmp_path_factory.mktemp("lab")
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    # -v: the nodes log at INFO, so the recordings hold log lines
    cmd = [sys.executable, "-m", "deploy.cli", "-v", "demo", "--scene", "lab", "--json"]
    proc = subprocess.run(
        [*cmd, "--duration", "4", "--record", str(out)],
        env=env,
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert proc.returncode == 0, why_the_demo_failed(proc)
    return out


def _foxglove_messages(path: Path):
    """(topic, schema name, schema, message) of every message on a Foxglove-typed channel."""
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            if schema is not None and schema.name.startswith("foxglove."):
                assert schema.encoding == "jsonschema" and channel.message_encoding == "json"
                yield channel.topic, schema.name, json.loads(schema.data), json.loads(message.data)


@pytest.mark.slow
@pytest.mark.untimed
def test_a_lab_recording_is_made_of_foxglove_messages(lab_session):
    counts: Counter[tuple[str, str]] = Counter()
    extras: dict[str, set] = defaultdict(set)
    for name in ("robot", "operator", "camera"):
        for topic, type_name, schema, message in _foxglove_messages(lab_session / f"{name}.mcap"):
            assert schema == foxglove.SCHEMAS[type_name], topic
            core = {k: v for k, v in message.items() if k in schema["properties"]}
            extras[topic] |= set(message) - set(core)
            parsed = check_message(type_name, core, schema)
            counts[(topic, type_name)] += 1
            if type_name == "foxglove.CompressedImage":
                assert parsed.format == "jpeg" and parsed.data[:2] == b"\xff\xd8"  # a JPEG
                assert parsed.frame_id == "overview"  # the lab's camera
            if type_name == "foxglove.RawImage":
                assert parsed.width * parsed.height * 4 == len(parsed.data) == 400
    got = {topic for topic, _ in counts}
    assert {
        "camera/image",
        "robot/pads/finger_1",
        "robot/pads/finger_2",
        "robot/tf/tcp",
        "robot/tf/finger_1",
        "robot/tf/finger_2",
        "robot/palm",
        "operator/palm",
        "log",
    } <= got, counts
    # only the camera keeps fields of its own beside Foxglove's (the dataset reads them)
    assert {t for t, e in extras.items() if e} == {"camera/image"}
    assert extras["camera/image"] >= {"t_capture_ns", "width", "height", "camera"}
    # the project's reader gives back the same records as before, views left out
    robot_channels = {c for c, _, _ in read_recording(lab_session / "robot.mcap")}
    assert not any(c.startswith(("robot/pads", "robot/tf", "robot/palm")) for c in robot_channels)
    assert {"robot/frame", "robot/arm", "robot/gripper"} <= robot_channels
    pics = [r for c, _, r in read_recording(lab_session / "camera.mcap") if c == "camera/image"]
    assert pics and isinstance(pics[0]["data"], bytes) and pics[0]["width"] > 0


@pytest.mark.slow
@pytest.mark.untimed
def test_the_lab_sessions_overview_camera_is_exported_and_lerobot_decodes_it(
    lab_session, lerobot, tmp_path
):
    """The same lab recording, exported: an ``observation.images.overview`` video feature, and
    LeRobot's own loader decodes every row's picture as the recorded picture the row holds
    (the lab's pictures carry no time stamp; test_export_roundtrip.py checks identity by stamp
    and the picture's time against its row's tactile frame)."""
    import bisect

    from common.recording.mcap_recorder import read_metadata
    from deploy.export.cli import export
    from deploy.export.resample import ExportConfig
    from robot_side.video.camera_recording import decode_jpeg

    fps = 30  # the export's rate
    meta_camera = read_metadata(lab_session / "camera.mcap")["deepxpalm.camera"]
    assert meta_camera["camera"] == "overview"
    root = tmp_path / "ds"
    summary = export([lab_session], root, ExportConfig(fps=fps, episodes="session"))
    key = "observation.images.overview"
    assert key in summary["features"]
    npz = tmp_path / "loaded.npz"
    lerobot.load(root, npz)
    with np.load(npz) as z:
        images = z[key]
        meta = json.loads(z["_meta"].tobytes())
    assert meta["features"][key]["shape"] == [240, 320, 3]
    assert images.shape == (summary["frames"], 3, 240, 320) and summary["frames"] > fps
    camera = [(t, r) for _, t, r in read_recording(lab_session / "camera.mcap")]
    times = [t for t, _ in camera]
    t_first = meta["episodes"][0]["deepxpalm/t_first_ns"]
    pictures: dict[int, np.ndarray] = {}
    for i, decoded in enumerate(images):
        t_row = t_first + round(i * 1e9 / fps)
        j = bisect.bisect_right(times, t_row) - 1
        assert j >= 0, f"row {i} before the camera's first picture"
        if j not in pictures:
            pictures[j] = decode_jpeg(camera[j][1]["data"]).astype(np.float32)
        held = pictures[j]
        assert held.std() > 5, "a blank picture: the lab's camera rendered nothing"
        error = np.abs(decoded.transpose(1, 2, 0) - held).mean()
        assert error < 4, f"row {i}: LeRobot's picture is {error:.1f} levels off the held one"
        # The picture is not held to its row's tactile frame here: both are the newest at or
        # before the row, so they differ only by a gap in one of the recorded streams, and the
        # lab's tactile frames come from a world that falls behind real time under load (a
        # 207 ms gap at the session's start, two busy loops beside it). test_export_roundtrip
        # holds that bound on the demo's tactile stream, read from its serial simulator.


def test_log_lines_are_foxglove_logs(tmp_path):
    """A recorder with log_level set keeps the process's lines at that level, not below."""
    import logging

    path = tmp_path / "log.mcap"
    rec = McapRecorder(path, log_level=logging.WARNING, fsync=False)
    logger = logging.getLogger("deepxpalm.test.foxglove")
    logger.warning("arm at %d mm", 12)
    logger.info("not kept")
    logger.error("boom")
    rec.close()
    logger.error("after close: not kept")
    lines = [(t, s, m) for topic, t, s, m in _foxglove_messages(path) if topic == "log"]
    assert [m["message"] for *_, m in lines] == ["arm at 12 mm", "boom"]
    assert [m["level"] for *_, m in lines] == [3, 4]  # WARNING, ERROR
    for type_name, schema, message in lines:
        assert type_name == "foxglove.Log"
        parsed = check_message(type_name, message, schema)
        assert parsed.name == "deepxpalm.test.foxglove" and parsed.line > 0
