"""The harness's commands plug into ``deepxpalm`` through an entry-point group.

The product never names the harness (tests/test_import_directions.py); the
``deepxpalm.commands`` group in pyproject.toml is the one place that does.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from deploy.cli import SUBCOMMANDS, commands_for, plugin_commands

REPO = Path(__file__).resolve().parents[2]


def _pyproject(tmp_path: Path, name: str, commands: str) -> Path:
    path = tmp_path / "pyproject.toml"
    path.write_text(
        f'[project]\nname = "{name}"\n\n[project.entry-points."deepxpalm.commands"]\n{commands}'
    )
    return path


def test_the_checkout_declares_the_harness_commands():
    found = plugin_commands(REPO / "pyproject.toml")
    assert found["bench"][0] == "harness.bench.cli"
    assert found["soak"][0] == "harness.soak"
    assert all(help_text for _, help_text in found.values())


def test_a_declared_command_is_found_and_a_broken_one_left_out(tmp_path, caplog):
    path = _pyproject(
        tmp_path,
        "deepxpalm",
        'bench = "harness.commands:BENCH"\n'
        'gone = "no_such_package.commands:GONE"\n'
        'demo = "harness.commands:SOAK"\n',
    )
    found = plugin_commands(path)
    assert found["bench"] == ("harness.bench.cli", found["bench"][1])
    assert "gone" not in found  # not installed: left out, with a warning naming it
    assert "'gone'" in caplog.text and "no_such_package" in caplog.text
    assert "demo" not in found  # a plug-in never shadows a product command
    assert SUBCOMMANDS["demo"][0] == "deploy.demo"


def test_a_product_command_never_looks_the_plug_ins_up():
    """``deepxpalm palm lift`` runs after the operator node dies: it pays for nothing else."""
    assert commands_for("palm") == SUBCOMMANDS
    assert {"bench", "soak"} <= set(commands_for("bench")) and "bench" in commands_for(None)


def test_another_projects_pyproject_adds_nothing(tmp_path):
    path = _pyproject(tmp_path, "someone-else", 'x = "harness.commands:BENCH"\n')
    assert "x" not in plugin_commands(path)


@pytest.mark.slow
@pytest.mark.untimed  # two interpreters start; no timing asserted
def test_the_commands_run_from_the_deepxpalm_command():
    """``deepxpalm bench --help`` and ``deepxpalm soak --help`` parse their own options."""
    for command, option in (("bench", "--quick"), ("soak", "--minutes")):
        out = subprocess.run(
            [sys.executable, "-m", "deploy.cli", command, "--help"],
            capture_output=True,
            text=True,
            timeout=120,
            cwd=REPO,
            check=True,
        ).stdout
        assert f"deepxpalm {command}" in out and option in out
