"""Every example a ``--help`` prints is a command line that runs.

The examples are collected from the parsers themselves: each subcommand's (and each nested
one's, ``keys show``, ``study run``) description and epilog lines that start with
``deepxpalm``, and each ``--set`` help's ``e.g. --set KEY=VALUE``. Every line parses with the
command's own parser. Those safe to run at once are run as a user would, through the installed
``deepxpalm``: each ``--set`` example with ``--print-config`` (a command without that option:
through the node whose section the key names, on the default scene), and the whole ``keys``
walk-through in a scratch folder (``/etc/deepxpalm`` moved there, the printed roster entries
pasted into its roster.toml). The rest (a simulator, the bench, a doctor against a PC's
devices) runs for minutes or needs the hardware, so only its parsing is checked here.
"""

from __future__ import annotations

import argparse
import functools
import os
import re
import shlex
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

from deploy.cli import _build_parser, commands_for

ROOT = Path(__file__).resolve().parents[2]
DEEPXPALM = str(Path(sys.executable).with_name("deepxpalm"))
SCENE = ROOT / "deploy" / "scenes" / "demo.toml"
#: the section a `--set` key names -> the command that prints that section's config
SECTION_COMMANDS = {"robot": "robot", "operator": "operator"}


@dataclass(frozen=True)
class Example:
    command: tuple[str, ...]  # the (sub)command whose help shows it: ("keys", "generate")
    argv: tuple[str, ...]  # the example, after "deepxpalm"

    def __str__(self) -> str:
        return "deepxpalm " + shlex.join(self.argv)


def _subparsers(parser: argparse.ArgumentParser, path: tuple[str, ...]):
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            seen: set[int] = set()
            for name, nested in action.choices.items():
                if id(nested) not in seen:  # an alias (study analyze) is the same parser
                    seen.add(id(nested))
                    yield from _subparsers(nested, (*path, name))


def _command_parser(name: str) -> argparse.ArgumentParser:
    parser = _build_parser(name, commands_for(name))
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices[name]


@functools.cache
def examples(name: str) -> tuple[list[Example], list[Example]]:
    """(example lines, --set examples as ``command --set KEY=VALUE``) of ``name``'s helps."""
    lines: list[Example] = []
    sets: list[Example] = []
    for path, parser in _subparsers(_command_parser(name), (name,)):
        for text in (parser.description or "", parser.epilog or ""):
            for line in text.splitlines():
                m = re.match(r"\s*deepxpalm\s+([^#]+)", line)
                if m and not line.lstrip().startswith("``"):
                    argv = tuple(shlex.split(m.group(1)))
                    if argv and argv[0] == name:
                        lines.append(Example(path, argv))
        for action in parser._actions:
            if action.dest == "overrides" and action.help:
                for value in re.findall(r"e\.g\. --set (\S+)", action.help):
                    sets.append(Example(path, (*path, "--set", value)))
    return lines, sets


#: the product's commands and the plugged-in ones; each one's parser is built in its test, not
#: at collection (that imports every command's module, in every test worker)
COMMANDS = sorted(commands_for("bench"))


def _run(argv: list[str], cwd: Path | None = None, **kw) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run(
        argv, capture_output=True, text=True, timeout=120, cwd=cwd or ROOT, env=env, **kw
    )


def test_the_helps_show_examples() -> None:
    """The collection finds what the helps show (a changed help format would hide them)."""
    shown = {e.argv[:2] for e in examples("keys")[0] + examples("doctor")[0]}
    assert ("keys", "generate") in shown and ("doctor", "--role") in shown, shown
    for name in ("robot", "operator", "video", "netsim"):
        assert [e.command for e in examples(name)[1]] == [(name,)]


@pytest.mark.parametrize("name", COMMANDS)
def test_every_example_line_parses(name: str) -> None:
    """Each example is a command line the command's parser takes (argparse exits 2 if not)."""
    parser = _build_parser(name, commands_for(name))
    for example in examples(name)[0]:
        try:
            args = parser.parse_args(list(example.argv))
        except SystemExit:
            pytest.fail(f"{example}: not a command line `deepxpalm {name}` takes")
        assert args.command == name


@pytest.mark.slow  # starts the command (a second or more each); no timing checked
@pytest.mark.untimed
@pytest.mark.parametrize("name", COMMANDS)
def test_every_set_example_is_a_known_setting(name: str) -> None:
    """``--set KEY=VALUE`` as the help shows it: the effective config printed, with the value."""
    for example in examples(name)[1]:
        parser = _command_parser(example.command[0])
        for nested in example.command[1:]:
            parser = dict(_subparsers(parser, ()))[(nested,)]
        argv = [DEEPXPALM, *example.argv]
        if "--print-config" not in parser._option_string_actions:
            # the command reads a scene's node sections: the node that owns the key prints it
            section = example.argv[-1].partition(".")[0]
            assert section in SECTION_COMMANDS, f"{example}: no command prints [{section}]"
            argv = [DEEPXPALM, SECTION_COMMANDS[section], "--config", str(SCENE)]
            argv += ["--set", example.argv[-1]]
        out = _run([*argv, "--print-config"])
        assert out.returncode == 0, f"{example}: {out.stderr.strip()}"
        key, _, value = example.argv[-1].partition("=")
        leaf = key.rpartition(".")[2]
        shown = [line for line in out.stdout.splitlines() if re.search(rf"\b{leaf} = ", line)]
        assert any(value.strip('"') in line for line in shown), (example, shown)


@pytest.mark.slow  # starts the command (a second or more each); no timing checked
@pytest.mark.untimed
def test_the_keys_walk_through_runs_as_shown(tmp_path: Path) -> None:
    """Every ``deepxpalm keys`` example in its help's order, in a scratch folder: the pairs, the
    allow, the signing key, a robot and an operator of a fleet, then the fabric's
    certificates from the roster their printed entries make."""
    etc = tmp_path / "etc" / "deepxpalm"
    etc.mkdir(parents=True)
    roster: list[str] = []
    keys = [e for e in examples("keys")[0] if e.command == ("keys",)]
    assert [e.argv[1] for e in keys] == [
        "generate", "generate", "allow", "generate-signing", "robot", "operator", "certs"
    ]  # fmt: skip
    for example in keys:
        argv = [a.replace("/etc/deepxpalm", str(etc)) for a in example.argv]
        if example.argv[1] == "certs":
            (tmp_path / "roster.toml").write_text("\n".join(roster))
        out = _run([DEEPXPALM, *argv], cwd=tmp_path)
        assert out.returncode == 0, f"{example}: {out.stderr.strip()}"
        if example.argv[1] in ("robot", "operator"):  # its entry, "to paste into roster.toml"
            roster.append(out.stdout)
    assert (etc / "operators").exists()
    assert (tmp_path / "fabric" / "ca.crt").is_file()
