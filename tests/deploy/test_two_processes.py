"""Both nodes from the example configs, as separate processes, the way the systemd units run them.

Only what cannot exist here is overridden on the command line: the devices
become simulators, the endpoints random loopback ports, and the keys come
from a temp dir made with `deepxpalm keys`. CURVE stays on. The tactile
board, the gripper and the arm are wire-level simulators driven by the real
serial, URCap and ur-rtde drivers. The servos are the in-process recording
bus: the Feetech SDK's reply timeout is fixed and on the wall clock, so its
pty fake bus misses replies on a loaded shared machine (the driver has its
own tests against it in tests/drivers).
"""

from __future__ import annotations

import json
import signal
import subprocess
import time
from pathlib import Path

import pytest
import zmq
from deploy_support import ENV, EXAMPLES, cli
from tests_support import ROBOT_BINDS_ITS_PORTS, link_to

from deploy.units.service import Service

pytestmark = pytest.mark.slow

LINK_UP = "operator link down -> ok"


def _wait_for_line(log: Path, text: str, procs: list[subprocess.Popen], timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if text in log.read_text(errors="replace"):
            return
        if any(p.poll() is not None for p in procs):
            break  # a node died: its log says why (see _stop)
        time.sleep(0.1)
    raise AssertionError(f"no {text!r} in {log.name}:\n{log.read_text(errors='replace')[-3000:]}")


def _stop(proc: subprocess.Popen, log: Path) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)  # what `systemctl stop` sends
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            raise AssertionError(f"{log.name}: did not stop on SIGTERM") from None
    assert proc.returncode == 0, log.read_text(errors="replace")[-3000:]


def _plain_subscriber_hears_nothing(endpoint: str, wait_s: float) -> bool:
    """Without the robot's key, a subscriber cannot even complete the handshake."""
    ctx = zmq.Context()
    sub = ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.LINGER, 0)
    sub.setsockopt(zmq.SUBSCRIBE, b"")
    sub.connect(endpoint)
    try:
        return not sub.poll(int(wait_s * 1000))
    finally:
        sub.close(0)
        ctx.term()


def test_example_configs_run_as_two_processes_over_curve(tmp_path, keys):
    robot_log, operator_log = tmp_path / "robot.log", tmp_path / "operator.log"
    robot_stats, operator_stats = tmp_path / "robot-stats.json", tmp_path / "operator-stats.json"
    robot_argv = [
        "-v",
        "robot",
        "--config",
        str(EXAMPLES / "robot.toml"),
        "--stats-file",
        str(robot_stats),
        "--set",
        'tactile={kind="simulated_serial", driver={connect_timeout_s=5.0}}',
        "--set",
        'gripper={kind="simulated"}',
        "--set",
        'arm={kind="simulated"}',
        "--set",
        f'link.security.secret_key_file="{keys.robot_secret}"',
        "--set",
        f'link.security.authorized_keys_dir="{keys.authorized}"',
        *ROBOT_BINDS_ITS_PORTS,  # said in its READY=1, and passed on to the operator
    ]
    operator_argv = cli(
        "-v",
        "operator",
        "--config",
        str(EXAMPLES / "operator.toml"),
        "--stats-file",
        str(operator_stats),
        "--set",
        'servos={kind="in_memory"}',
        "--set",
        f'link.security.secret_key_file="{keys.operator_secret}"',
        "--set",
        f'link.security.server_public_key_file="{keys.robot_public}"',
    )
    service = Service("robot", robot_argv, robot_log, env=ENV, watchdog=False)
    ends = service.up(60).endpoints
    robot = service.popen
    with operator_log.open("wb") as olog:
        operator_argv += link_to(ends)
        operator = subprocess.Popen(operator_argv, stdout=olog, stderr=subprocess.STDOUT, env=ENV)
        try:
            _wait_for_line(robot_log, LINK_UP, [robot, operator], timeout_s=20)
            assert _plain_subscriber_hears_nothing(ends["telemetry"], wait_s=1.5)
            time.sleep(1.0)  # stimuli flow meanwhile
        finally:
            _stop(operator, operator_log)
            time.sleep(0.6)  # the robot's 250 ms deadman sees the operator go
            _stop(robot, robot_log)
            service.close()

    op = json.loads(operator_stats.read_text())
    rb = json.loads(robot_stats.read_text())
    # The operator heard the robot over CURVE and drove its servos from the stimuli.
    assert op["stimuli_received"] > 0, op
    assert op["heartbeats_received"] > 0, op
    assert op["servo_writes"] > 0, op
    # The robot rendered frames from the serial board and heard the operator: its
    # deadman tripped exactly once, when the operator stopped (it counts only after contact).
    assert rb["frames_processed"] > 0 and rb["stimuli_published"] > 0, rb
    assert rb["deadman_trips"] == 1, rb
    # Both froze their startup heap, so no full collection walks it mid-loop.
    for stats in (op, rb):
        assert stats["gc_frozen_objects"] > 10_000, stats
    # Nothing was rejected or failed on either side.
    for stats in (op, rb):
        for key in ("decode_errors", "messages_unexpected", "commands_rejected", "gripper_errors"):
            assert stats.get(key, 0) == 0, (key, stats)
    for log in (robot_log, operator_log):
        text = log.read_text(errors="replace")
        assert "Traceback" not in text and " ERROR " not in text, text[-3000:]
