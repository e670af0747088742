"""A robot's keys from `deepxpalm keys`, and its stream signed by default through a relay.

The real CLI in subprocesses: the keys and roster entries it writes, and
whether a robot or an operator node in relay mode starts without the
robot's signing key.
"""

from __future__ import annotations

import re
import subprocess
import sys

import pytest

from common.roster import load_roster
from common.signing import load_public_key, load_signer
from deploy.fleet import Fleet

pytestmark = [pytest.mark.slow, pytest.mark.timeout(60), pytest.mark.parallel]


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "deploy.cli", *args], capture_output=True, text=True, timeout=30
    )


def test_keys_robot_makes_both_pairs_once_and_prints_an_entry_the_roster_takes(tmp_path):
    keys = tmp_path / "keys"
    first = _cli("keys", "robot", "--dir", str(keys), "--name", "cell1", "--names", "cell1-cam")
    assert first.returncode == 0, first.stderr
    made = {p.name: p.read_bytes() for p in keys.iterdir()}
    assert set(made) == {"cell1.key", "cell1.key_secret", "cell1.sign", "cell1.sign_secret"}
    assert all((keys / n).stat().st_mode & 0o077 == 0 for n in made if n.endswith("_secret"))
    again = _cli("keys", "robot", "--dir", str(keys), "--name", "cell1", "--names", "cell1-cam")
    assert again.stdout == first.stdout, "the same keys, the same entry"
    assert {p.name: p.read_bytes() for p in keys.iterdir()} == made, "nothing replaced"
    operator = _cli("keys", "operator", "--dir", str(keys), "--name", "alice", "--role", "observer")
    assert operator.returncode == 0, operator.stderr

    roster = tmp_path / "roster.toml"
    roster.write_text(operator.stdout + "\n" + first.stdout)  # its comments are TOML comments
    loaded = load_roster(roster)
    assert loaded.robots[0].wire_names() == {b"cell1", b"cell1-cam"}
    assert loaded.operators[0].signing_key == load_public_key(keys / "alice.sign")
    secret = re.search(r'signing_key_file = "([^"]+)"', first.stdout).group(1)
    assert load_signer(secret).public == load_public_key(keys / "cell1.sign")


def _without(path, setting: str, instead: str = "") -> None:
    path.write_text(re.sub(rf'{setting} = ".*"\n', instead, path.read_text()))


def test_a_robot_and_an_operator_through_a_relay_refuse_an_unsigned_stream_unless_told(tmp_path):
    fleet = Fleet(robots=["cell1"], operators={"alice": "observer"}, workdir=tmp_path)
    robot = fleet.robot_config("cell1", None)
    _without(robot, "signing_key_file")
    refused = _cli("robot", "--config", str(robot), "--duration", "0.3")
    assert refused.returncode != 0 and "signs its stream" in refused.stderr, refused.stderr
    relay_mode = 'mode = "relay"\n'
    robot.write_text(robot.read_text().replace(relay_mode, relay_mode + "unsigned_stream = true\n"))
    told = _cli("robot", "--config", str(robot), "--duration", "0.3")
    assert told.returncode == 0, told.stderr
    assert "stream is not signed" in told.stderr

    operator = fleet.workdir / "alice@cell1.toml"
    fleet.start_operator("alice", "cell1")  # writes its config; no relay, so it only waits
    fleet.stop("alice@cell1")
    _without(operator, "robot_key_file")
    refused = _cli("operator", "--config", str(operator), "--duration", "0.3")
    assert refused.returncode != 0 and "must be signed" in refused.stderr, refused.stderr
