"""The ``deepxpalm`` command's options do what their help says, run as a user runs them.

``--record`` only where a command records; ``-v`` before or after the subcommand;
``--version``; ``keys show`` on a file that is no key, and a node's missing config file or
malformed value: one line, exit code 2, no traceback.
"""

from __future__ import annotations

import os
import subprocess
import sys
from importlib.metadata import version
from pathlib import Path

import pytest

# each test starts the command once or more (a second or more each on a loaded 2-core machine);
# no timing checked
pytestmark = [pytest.mark.slow, pytest.mark.untimed]

ROOT = Path(__file__).resolve().parents[2]
DEEPXPALM = str(Path(sys.executable).with_name("deepxpalm"))


def _run(*argv: str, cwd: Path = ROOT, timeout: float = 120) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run(
        [DEEPXPALM, *argv], capture_output=True, text=True, timeout=timeout, cwd=cwd, env=env
    )


def test_version_prints_the_installed_version() -> None:
    out = _run("--version")
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == f"deepxpalm {version('deepxpalm')}"


@pytest.mark.parametrize("command", ["robot", "operator"])
def test_the_nodes_offer_record(command: str) -> None:
    assert "--record FILE" in _run(command, "--help").stdout


@pytest.mark.parametrize("command", ["video", "netsim", "record", "router"])
def test_commands_that_do_not_record_refuse_record(command: str, tmp_path: Path) -> None:
    """No ``--record`` in their help, and given one, a usage error rather than silence."""
    options = _run(command, "--help").stdout.split("Configuration:")[0]  # not the config's notes
    assert "--record" not in options
    out = _run(command, "--record", str(tmp_path / "x.mcap"), "--print-config")
    assert out.returncode == 2 and "unrecognized arguments: --record" in out.stderr, out.stderr


def test_netsim_stops_after_duration_as_every_command_does() -> None:
    out = _run("netsim", "--duration", "7", "--print-config")
    assert out.returncode == 0, out.stderr
    assert "duration_s = 7.0" in out.stdout


def test_verbose_before_and_after_the_subcommand() -> None:
    """``-v`` before the command, after it, or both (``-vv``, debug): the node logs INFO."""
    ports = ['robot.link.telemetry_endpoint="tcp://127.0.0.1:0"',
             'robot.link.command_endpoint="tcp://127.0.0.1:0"']  # fmt: skip
    node = ["--duration", "0.5", "--set", ports[0], "--set", ports[1]]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    runs = {
        name: subprocess.Popen(
            [DEEPXPALM, *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
        )
        for name, argv in {
            "none": ["robot", *node],
            "before": ["-v", "robot", *node],
            "after": ["robot", "-v", *node],
            "both": ["-v", "robot", "-v", *node],
        }.items()
    }
    logs = {}
    for name, proc in runs.items():
        _, err = proc.communicate(timeout=180)
        assert proc.returncode == 0, (name, err[-2000:])
        logs[name] = err
    assert " INFO " not in logs["none"], logs["none"][-2000:]
    for name in ("before", "after", "both"):
        assert " INFO " in logs[name] and "robot node up" in logs[name], logs[name][-2000:]
    assert " DEBUG " in logs["both"] and " DEBUG " not in logs["after"]


def test_verbose_after_a_nested_subcommand(tmp_path: Path) -> None:
    out = _run("keys", "generate", "-v", "--dir", str(tmp_path), "--name", "k")
    assert out.returncode == 0, out.stderr
    assert _run("keys", "show", str(tmp_path / "k.key"), "-v").returncode == 0


def _bad_key_files(tmp_path: Path) -> dict[str, Path]:
    (tmp_path / "empty.key").write_text("")
    (tmp_path / "binary.key").write_bytes(bytes(range(256)) * 4)
    (tmp_path / "toml.key").write_text('[robot]\nmode = "bind"\n')
    (tmp_path / "short.key").write_text('metadata\ncurve\n    public-key = "abc"\n')
    (tmp_path / "hex.sign").write_text("12ab\n")
    return {
        "missing": tmp_path / "no-such.key",
        "a directory": tmp_path,
        "empty": tmp_path / "empty.key",
        "binary": tmp_path / "binary.key",
        "a config, not a key": tmp_path / "toml.key",
        "a truncated public key": tmp_path / "short.key",
        "a truncated signing key": tmp_path / "hex.sign",
    }


def test_keys_show_on_a_bad_file_says_so_in_one_line(tmp_path: Path) -> None:
    for what, path in _bad_key_files(tmp_path).items():
        out = _run("keys", "show", str(path))
        lines = out.stderr.strip().splitlines()
        assert out.returncode == 2, (what, out.returncode, out.stderr)
        assert len(lines) == 1 and "Traceback" not in out.stderr, (what, out.stderr)
        assert str(path) in lines[0] and not out.stdout, (what, out.stderr)


def test_keys_show_prints_each_kind_of_key(tmp_path: Path) -> None:
    assert _run("keys", "generate", "--dir", str(tmp_path), "--name", "r").returncode == 0
    assert _run("keys", "generate-signing", "--dir", str(tmp_path), "--name", "s").returncode == 0
    public = _run("keys", "show", str(tmp_path / "r.key")).stdout.strip()
    assert len(public) == 40
    assert _run("keys", "show", str(tmp_path / "r.key_secret")).stdout.strip() == public
    signing = (tmp_path / "s.sign").read_text().strip()
    assert _run("keys", "show", str(tmp_path / "s.sign")).stdout.strip() == signing
    # a secret signing key shows its public key, never the secret
    assert _run("keys", "show", str(tmp_path / "s.sign_secret")).stdout.strip() == signing


@pytest.mark.parametrize(
    ("command", "bad_value"),
    [
        ("robot", "robot.link.heartbeat_rate_hz=fast"),
        ("operator", "operator.link.stale_after_ms=banana"),
        ("router", "router.max_sessions=many"),
        ("record", "recorder.robots=7"),
        ("netsim", "netsim.seed=lucky"),
        ("video", "video.port=eighty"),
    ],
)
def test_a_missing_config_file_or_a_malformed_value_is_one_line_and_exit_code_2(
    tmp_path, command: str, bad_value: str
) -> None:
    missing = _run(command, "--config", str(tmp_path / "nowhere.toml"), "--print-config")
    assert missing.returncode == 2, (missing.returncode, missing.stderr)
    assert missing.stderr.strip().count("\n") == 0 and "nowhere.toml" in missing.stderr
    malformed = _run(command, "--set", bad_value, "--print-config")
    assert malformed.returncode == 2, (malformed.returncode, malformed.stderr)
    lines = malformed.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in malformed.stderr, malformed.stderr
    assert bad_value.split("=")[0].split(".")[-1] in lines[0], lines
