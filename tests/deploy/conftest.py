"""Fixtures for the deploy tests: CURVE keys in a temp dir, nodes on random loopback ports."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from pathlib import Path

import pytest
from deploy_support import loopback


@dataclass
class Keys:
    directory: Path
    robot_secret: Path
    robot_public: Path
    operator_secret: Path
    operator_public: Path
    authorized: Path


@pytest.fixture
def keys(tmp_path: Path) -> Keys:
    """A robot pair, an operator pair, and the operator allowed on the robot (as in docs)."""
    from deploy.keys_cli import allow, generate

    directory = tmp_path / "keys"
    robot_public, robot_secret = generate(directory, "robot")
    operator_public, operator_secret = generate(directory, "operator")
    authorized = directory / "operators"
    allow(operator_public, authorized)
    return Keys(directory, robot_secret, robot_public, operator_secret, operator_public, authorized)


@pytest.fixture
def robot_in_thread():
    """Start a light robot node (scripted pads, no gripper or arm) in a thread; stopped after."""
    started: list[tuple[threading.Event, threading.Thread]] = []

    def start(tel: int, cmd: int, security: dict | None = None):
        from common.config.typed import from_dict
        from robot_side.node import build_robot_node
        from robot_side.node.config import RobotConfig

        config = from_dict(
            RobotConfig,
            {
                "render": {"mode": "mask_ground_truth"},
                "link": {
                    "telemetry_endpoint": loopback(tel),
                    "command_endpoint": loopback(cmd),
                    "security": security or {},
                },
            },
        )
        node = build_robot_node(config)
        stop = threading.Event()
        thread = threading.Thread(target=node.run, args=(stop, 30.0), daemon=True)
        thread.start()
        started.append((stop, thread))
        deadline = time.monotonic() + 10
        while node.sub is None and thread.is_alive() and time.monotonic() < deadline:
            time.sleep(0.01)  # until both ports are bound: a probe before that is refused
        return node

    yield start
    for stop, thread in started:
        stop.set()
        thread.join(10)


@pytest.fixture
def operator_in_thread():
    """Start an operator node (in-memory servos) in a thread; stopped after."""
    started: list[tuple[threading.Event, threading.Thread]] = []

    def start(tel: int, cmd: int, security: dict | None = None):
        from common.config.typed import from_dict
        from operator_side.node import build_operator_node
        from operator_side.node.config import OperatorConfig

        config = from_dict(
            OperatorConfig,
            {
                "link": {
                    "telemetry_endpoint": loopback(tel),
                    "command_endpoint": loopback(cmd),
                    "security": security or {},
                }
            },
        )
        node = build_operator_node(config)
        stop = threading.Event()
        thread = threading.Thread(target=node.run, args=(stop, 30.0), daemon=True)
        thread.start()
        started.append((stop, thread))
        return node

    yield start
    for stop, thread in started:
        stop.set()
        thread.join(10)
