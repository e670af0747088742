"""Fixtures the system tests share."""

from __future__ import annotations

import pytest

from common.keys.curve import SecurityConfig
from deploy.keys_cli import allow, generate


@pytest.fixture
def keys(tmp_path):
    """CURVE settings for a robot, its allowed operator and a stranger the robot does not know."""
    robot_pub, robot_sec = generate(tmp_path / "robot", "robot")
    op_pub, op_sec = generate(tmp_path / "operator", "operator")
    _, stranger_sec = generate(tmp_path / "stranger", "stranger")
    authorized = tmp_path / "authorized"
    allow(op_pub, authorized)
    return {
        "robot": SecurityConfig(
            mode="curve", secret_key_file=robot_sec, authorized_keys_dir=authorized
        ),
        "operator": SecurityConfig(
            mode="curve", secret_key_file=op_sec, server_public_key_file=robot_pub
        ),
        "stranger": SecurityConfig(
            mode="curve", secret_key_file=stranger_sec, server_public_key_file=robot_pub
        ),
    }
