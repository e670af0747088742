"""Secrets on the operator's and the robot's machine, checked through the real commands.

- ``--print-config`` never shows a token (set in the file or on the command line);
- a config file holding a token that other users can read is refused, naming the fix;
- a secret key file is never open in another mode than 0600, not even for an instant
  (its mode read as each write opens it, under a permissive umask);
- the robot node refuses to put an arm behind a plain, unsigned command port.
"""

from __future__ import annotations

import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from common.errors import ConfigError

TOKEN = "a-page-token-nobody-else-may-see-0123"


def _cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "deploy.cli", *args],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=cwd,
    )


@pytest.mark.slow
@pytest.mark.untimed
def test_print_config_shows_no_token_and_a_readable_file_holding_one_is_refused(tmp_path):
    config = tmp_path / "operator.toml"
    config.write_text(
        f'[operator.dashboard]\ntoken = "{TOKEN}"\n'
        f'video_url = "ws://127.0.0.1:8890/?token={TOKEN}x"\n'
    )
    config.chmod(0o644)
    refused = _cli("operator", "--config", str(config), "--print-config")
    assert refused.returncode != 0
    assert "other users can read it" in refused.stderr and f"chmod 600 {config}" in refused.stderr
    assert "dashboard.token" in refused.stderr and TOKEN not in refused.stderr
    config.chmod(0o600)
    shown = _cli("operator", "--config", str(config), "--print-config")
    assert shown.returncode == 0, shown.stderr
    assert TOKEN not in shown.stdout + shown.stderr
    assert "# token = (set; not shown)" in shown.stdout
    assert 'video_url = "ws://127.0.0.1:8890/"' in shown.stdout
    # on the command line: not shown either (and no file holds it)
    flag = _cli("operator", "--set", f'dashboard.token="{TOKEN}"', "--print-config")
    assert flag.returncode == 0 and TOKEN not in flag.stdout


class OpenWatch:
    """Every file this process opens for writing, and its mode right as it was opened (what
    another user racing to open it would be allowed), through both ``open`` and ``os.open``."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        import builtins

        self.modes: list[tuple[str, int]] = []
        real_open, real_os_open = builtins.open, os.open

        def watched_open(file, mode="r", *args, **kw):
            f = real_open(file, mode, *args, **kw)
            if any(c in mode for c in "wax+") and not isinstance(file, int):
                self.modes.append((Path(file).name, stat.S_IMODE(os.fstat(f.fileno()).st_mode)))
            return f

        def watched_os_open(path, flags, mode=0o777, *args, **kw):
            fd = real_os_open(path, flags, mode, *args, **kw)
            if flags & (os.O_WRONLY | os.O_RDWR):
                self.modes.append((Path(path).name, stat.S_IMODE(os.fstat(fd).st_mode)))
            return fd

        monkeypatch.setattr(builtins, "open", watched_open)
        monkeypatch.setattr(os, "open", watched_os_open)


@pytest.mark.slow
def test_secret_key_files_are_0600_from_their_creation(tmp_path, monkeypatch):
    from common.wire.signing import generate_key_files
    from deploy.keys_cli import generate, machine_keys

    directory = tmp_path / "keys"
    directory.mkdir()
    old = os.umask(0o022)  # what most shells run with: pyzmq's secret came out 0644
    watch = OpenWatch(monkeypatch)
    try:
        generate(directory, "robot")
        generate_key_files(directory, "operator")
        secret = directory / "robot.key_secret"
        secret.chmod(0o644)  # a widened old pair, replaced by --force: never written into
        generate(directory, "robot", force=True)
        machine_keys(directory, "cell1")
    finally:
        os.umask(old)
        monkeypatch.undo()
    written = [(n, oct(m)) for n, m in watch.modes if "secret" in n]
    assert len(written) == 5, watch.modes
    assert all(m == "0o600" for _, m in written), written
    for path in directory.iterdir():
        if "secret" in path.name:
            assert stat.S_IMODE(path.stat().st_mode) == 0o600, path
    assert {p.name for p in directory.iterdir()} == {
        f"{name}.{kind}"
        for name, kinds in (
            ("robot", ("key", "key_secret")),
            ("operator", ("sign", "sign_secret")),
            ("cell1", ("key", "key_secret", "sign", "sign_secret")),
        )
        for kind in kinds
    }  # no temporary file left behind
    import zmq.auth

    public, secret_key = zmq.auth.load_certificate(directory / "robot.key_secret")
    assert (
        secret_key is not None and zmq.auth.load_certificate(directory / "robot.key")[0] == public
    )


@pytest.mark.slow
@pytest.mark.untimed
def test_the_robot_refuses_an_arm_behind_a_plain_unsigned_command_port(tmp_path):
    from common.config.typed import from_dict
    from robot_side.node.config import RobotConfig
    from robot_side.node.link_setup import check_command_access

    def config(**link) -> RobotConfig:
        return from_dict(RobotConfig, {"arm": {"kind": "simulated"}, "link": link}, where="robot")

    with pytest.raises(ConfigError, match="allow_plain_commands") as e:
        check_command_access(config())
    assert "security.mode = 'curve'" in str(e.value) and "roster_file" in str(e.value)
    check_command_access(config(allow_plain_commands=True))  # said so: a warning only
    check_command_access(from_dict(RobotConfig, {}, where="robot"))  # no arm: nothing to steer
    # and through the real command, before any device is opened
    out = _cli("robot", "--set", 'arm={kind="simulated"}', "--duration", "1")
    assert out.returncode != 0 and "allow_plain_commands" in out.stderr
