"""Across sites the robot's stream is signed by default: a node refuses to start otherwise.

The real CLI in subprocesses, with the configs ``Fleet`` writes for the fabric:
a robot without its signing key, or an operator without the robot's public
key, stops at start with the setting to change, before it opens its session;
told ``link.unsigned_stream = true``, each runs (through a real router, since a
fabric node that never reaches its router exits).
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from harness.fleet import Fleet

pytestmark = [pytest.mark.slow, pytest.mark.timeout(120)]

FABRIC_MODE = 'mode = "fabric"\n'


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "deploy.cli", *args], capture_output=True, text=True, timeout=60
    )


def _without(path: Path, setting: str) -> None:
    path.write_text(re.sub(rf'{setting} = ".*"\n', "", path.read_text()))


def _told_unsigned(path: Path) -> None:
    """``link.unsigned_stream = true`` beside the link's mode (the one ``mode`` in the file)."""
    text = path.read_text()
    assert text.count(FABRIC_MODE) == 1, text
    path.write_text(text.replace(FABRIC_MODE, FABRIC_MODE + "unsigned_stream = true\n"))


def test_a_robot_and_an_operator_on_the_fabric_refuse_an_unsigned_stream_unless_told(tmp_path):
    fleet = Fleet(robots=["cell1"], operators={"alice": "observer"}, workdir=tmp_path)
    with fleet:
        fleet.start_router()
        robot = fleet.robot_config("cell1", None)
        _without(robot, "signing_key_file")
        refused = _cli("robot", "--config", str(robot), "--duration", "0.3")
        assert refused.returncode != 0, refused.stderr
        assert "signs its stream" in refused.stderr, refused.stderr
        assert "unsigned_stream" in refused.stderr, "the setting that takes the risk is named"

        operator = fleet.workdir / "alice@cell1.toml"
        fleet.start_operator("alice", "cell1")  # writes its config
        fleet.stop("alice@cell1")
        _without(operator, "robot_key_file")
        refused = _cli("operator", "--config", str(operator), "--duration", "0.3")
        assert refused.returncode != 0, refused.stderr
        assert "must be signed" in refused.stderr, refused.stderr
        assert "robot_key_file" in refused.stderr and "unsigned_stream" in refused.stderr

        _told_unsigned(robot)
        told = _cli("robot", "--config", str(robot), "--duration", "0.3")
        assert told.returncode == 0, told.stderr
        assert "stream is not signed" in told.stderr, told.stderr
        _told_unsigned(operator)
        told = _cli("operator", "--config", str(operator), "--duration", "0.3")
        assert told.returncode == 0, told.stderr
