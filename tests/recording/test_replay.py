"""Replay: a real session's recordings check out against the pipeline; tampering does not."""

from __future__ import annotations

import argparse
import threading
import time

import numpy as np
import pytest
from tests_support import free_ports

from common.recording.mcap_recorder import (
    McapRecorder,
    node_recorder,
    read_metadata,
    read_recording,
)
from common.wire.codec import encode
from deploy import replay
from operator_side.node import OperatorNode
from operator_side.node.config import OperatorConfig
from operator_side.servos.in_memory import InMemoryServoBus
from robot_side.node import RobotNode
from robot_side.node.config import RobotConfig
from robot_side.tactile.script import GraspScript, GraspStep
from robot_side.tactile.scripted import ScriptedTactileConfig, ScriptedTactileSensor

pytestmark = pytest.mark.slow


def _script() -> GraspScript:
    return GraspScript(
        grasps=[
            GraspStep(pattern=p, grip_level=20, ramp_s=0.15, hold_s=0.4, release_s=0.1, pause_s=0.1)
            for p in (6, 3, 9)
        ],
        loop=True,
        start_delay_s=0.1,
    )


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """Both nodes in threads for 2.5 s, each recording, as `deepxpalm demo --record` does."""
    out = tmp_path_factory.mktemp("session")
    tel, cmd = (f"tcp://127.0.0.1:{p}" for p in free_ports(2))
    rc = RobotConfig()
    rc.render.mode = "mask_ground_truth"
    rc.link.telemetry_endpoint, rc.link.command_endpoint = tel, cmd
    oc = OperatorConfig()
    oc.link.telemetry_endpoint, oc.link.command_endpoint = tel, cmd
    robot_rec = node_recorder(out / "robot.mcap", rc, "robot")
    op_rec = node_recorder(out / "operator.mcap", oc, "operator")
    sensor = ScriptedTactileSensor(ScriptedTactileConfig(script=_script(), seed=5))
    robot = RobotNode(rc, sensor, recorder=robot_rec)
    operator = OperatorNode(oc, InMemoryServoBus(), recorder=op_rec)
    stop = threading.Event()
    threads = [
        threading.Thread(target=robot.run, args=(stop,), daemon=True),
        threading.Thread(target=operator.run, args=(stop,), daemon=True),
    ]
    for t in threads:
        t.start()
    time.sleep(2.5)
    stop.set()
    for t in threads:
        t.join(timeout=5)
    robot_rec.close()
    op_rec.close()
    return out


def test_a_robot_recording_replays_without_mismatch(session):
    s = replay.check(session / "robot.mcap")
    assert s["node"] == "robot" and s["closed_cleanly"]
    assert s["mismatches"] == 0, s["examples"]
    assert s["checked"]["stimuli_matching"] > 20


def test_an_operator_recording_replays_without_mismatch(session):
    s = replay.check(session / "operator.mcap")
    assert s["node"] == "operator"
    assert s["mismatches"] == 0, s["examples"]
    assert s["checked"]["servo_writes_consistent"] > 20
    assert s["checked"]["stimuli_rendered"] > 20


def _copy_with(src, dst, change):
    """Rewrite a recording through ``change(channel, record) -> record``, keeping its config."""
    meta = {k: v for k, v in read_metadata(src).items() if k != "deepxpalm.clock"}
    with McapRecorder(dst, metadata=meta) as rec:
        for channel, t, record in read_recording(src):
            record.pop("decoded", None)
            rec.write(channel, t, change(channel, record))


def test_a_tampered_stimulus_is_reported_and_fails_check(session, tmp_path, capsys):
    done = []

    def change(channel, record):
        if channel == "robot/stimulus" and not done:
            from common.wire.codec import decode

            msg = decode(record["wire"])
            if msg.contact and not msg.keyframe:
                msg.stimulus = np.where(msg.stimulus > 0, msg.stimulus + 0.5, 0).astype(np.float32)
                record["wire"] = encode(msg)
                done.append(msg.seq)
        return record

    _copy_with(session / "robot.mcap", tmp_path / "bad.mcap", change)
    assert done
    s = replay.check(tmp_path / "bad.mcap")
    assert s["mismatch_kinds"] == {"stimulus": 1}
    args = argparse.Namespace(
        file=tmp_path / "bad.mcap",
        check=True,
        atol=1e-5,
        no_classifier=True,
        calibration=None,
        publish=None,
        recover=None,
        json=False,
    )
    assert replay.run(args) == 1
    assert "MISMATCHES" in capsys.readouterr().out


def test_a_servo_jump_is_reported(session, tmp_path):
    jumped = []

    def change(channel, record):
        if channel == "operator/servo_goals" and len(jumped) < 1 and record["counts"][0] > 1200:
            record["counts"] = record["counts"].copy()
            record["counts"][0] -= 150  # far more than one cycle's step
            jumped.append(1)
        return record

    _copy_with(session / "operator.mcap", tmp_path / "bad.mcap", change)
    s = replay.check(tmp_path / "bad.mcap")
    assert s["mismatch_kinds"].get("servo_step", 0) >= 1


def test_a_changed_renderer_setting_shows_up(session, tmp_path):
    """A recording checked against other rendering settings must not pass silently."""
    meta = read_metadata(session / "robot.mcap")
    text = meta["deepxpalm.node"]["config_toml"].replace(
        'method = "antialiased"', 'method = "area"'
    )
    assert text != meta["deepxpalm.node"]["config_toml"]
    with McapRecorder(
        tmp_path / "r.mcap", metadata={"deepxpalm.node": {"node": "robot", "config_toml": text}}
    ) as rec:
        for channel, t, record in read_recording(session / "robot.mcap"):
            rec.write(channel, t, record)
    assert replay.check(tmp_path / "r.mcap")["mismatches"] > 0


def test_publish_drives_a_live_operator_node(session):
    (port,) = free_ports(1)
    endpoint = f"tcp://127.0.0.1:{port}"
    oc = OperatorConfig()
    oc.link.telemetry_endpoint = endpoint
    (cmd_port,) = free_ports(1)
    oc.link.command_endpoint = f"tcp://127.0.0.1:{cmd_port}"
    bus = InMemoryServoBus()
    operator = OperatorNode(oc, bus)
    stop = threading.Event()
    t = threading.Thread(target=operator.run, args=(stop,), daemon=True)
    t.start()
    try:
        sent = replay.publish(session / "robot.mcap", endpoint, speed=2.0, wait_subscriber_s=5)
        time.sleep(0.3)
    finally:
        stop.set()
        t.join(timeout=5)
    n_stimuli = sum(
        1 for c, _, _ in read_recording(session / "robot.mcap") if c == "robot/stimulus"
    )
    assert sent["stimuli"] == n_stimuli
    assert operator.counters["stimuli_received"] >= 0.95 * n_stimuli
    assert operator.counters["stimuli_matching_truth"] > 0
    assert operator.counters["heartbeats_received"] > 0
    assert bus.status()["refused"] == 0
    # the palm moved: some write left the lifted pose
    retract = operator.renderer.retract_counts
    assert any(list(r.goals.values()) != retract.tolist() for r in bus.records)
