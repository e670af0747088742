"""The ``deepxpalm`` command.

Each subcommand lives in its own module with ``add_arguments(parser)`` and
``run(args) -> int``; only the chosen one is imported, so ``deepxpalm
operator`` never pays for (or depends on) what the robot needs.

Commands from outside the product (the test harness's ``bench`` and
``soak``) plug in through the ``deepxpalm.commands`` entry-point group, so
the product never names them: each entry point loads a ``(module, help)``
pair like the ones in ``SUBCOMMANDS``. They are looked up only when the
command asked for is not the product's own, so ``deepxpalm palm lift`` (run
after the operator node dies) or ``deepxpalm robot`` never pays for the lookup.
"""

from __future__ import annotations

import argparse
import faulthandler
import importlib
import io
import logging
import re
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from common.errors import ConfigError, DeepXPalmError
from common.logs import configure as configure_logging

if TYPE_CHECKING:
    from importlib.metadata import EntryPoint

log = logging.getLogger(__name__)

#: subcommand -> (module, one-line help)
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("deploy.demo", "run both nodes, simulated devices and the link simulator"),
    "robot": ("robot_side.node_cli", "run the robot node (tactile pads, gripper, arm)"),
    "operator": ("operator_side.node_cli", "run the operator node (LinkGlide)"),
    "palm": (
        "operator_side.palm_cli",
        "lift: every LinkGlide linkage off the palm, with no node running (after it died)",
    ),
    "video": ("robot_side.video.cli", "stream a camera from the robot PC to the dashboard"),
    "router": (
        "router_side.cli",
        "run the fabric's Zenoh router: robots and operators of several sites meet there",
    ),
    "record": ("operator_side.record_cli", "keep every robot's stream from the fabric, to a file"),
    "topic": (
        "deploy.topic_cli",
        "look at the wire: each topic's rate, sessions and messages (ros2 topic hz/echo)",
    ),
    "view": ("deploy.view_cli", "a robot's link and a session's recordings, live in Foxglove"),
    "netsim": ("common.netsim.cli", "run the latency simulator between the two nodes"),
    "train": ("robot_side.perception.cli", "generate data, train and report the tilt CNN"),
    "collect": (
        "deploy.collect_cli",
        "collect labelled frames of every pattern and grip level (lab world or robot)",
    ),
    "devices": ("deploy.devices_cli", "list, connect to and report a scene's devices"),
    "calibrate": (
        "operator_side.servos.calibrate_cli",
        "set and store LinkGlide servo calibration",
    ),
    "sim": ("deploy.sim_cli", "run one device simulator on its real wire, standalone"),
    "keys": ("deploy.keys_cli", "make CURVE key pairs and allow operators on the robot"),
    "doctor": ("deploy.doctor", "check this machine before a session: config, devices, keys, peer"),
    "replay": ("deploy.replay", "check a recording against the pipeline, or publish it again"),
    "export": ("deploy.export.cli", "recorded sessions -> a LeRobot dataset (docs/datasets.md)"),
    "study": ("operator_side.study.cli", "run the palm perception study and analyse it"),
}

#: the entry-point group other packages add ``deepxpalm`` subcommands through
COMMAND_GROUP = "deepxpalm.commands"
#: a source checkout's pyproject.toml, when the command runs from one
CHECKOUT_PYPROJECT = Path(__file__).resolve().parents[1] / "pyproject.toml"


def _declared_in(pyproject: Path) -> list[EntryPoint]:
    """The group's entry points as a checkout's own pyproject.toml declares them.

    An editable install's metadata is written at install time; a checkout whose
    pyproject.toml gained a command since (or a tree put first on PYTHONPATH)
    would not see it without this.
    """
    import tomllib
    from importlib.metadata import EntryPoint

    try:
        project = tomllib.loads(pyproject.read_text()).get("project", {})
    except (OSError, tomllib.TOMLDecodeError):
        return []
    if project.get("name") != "deepxpalm":
        return []
    declared = project.get("entry-points", {}).get(COMMAND_GROUP, {})
    return [EntryPoint(n, v, COMMAND_GROUP) for n, v in declared.items()]


def plugin_commands(pyproject: Path = CHECKOUT_PYPROJECT) -> dict[str, tuple[str, str]]:
    """subcommand -> (module, help) for every command in ``COMMAND_GROUP``.

    Installed entry points first, then the checkout's own declarations over
    them. A command whose package is not installed is left out with a warning
    that says so; one that would shadow a product command is refused.
    """
    from importlib.metadata import entry_points

    points = {ep.name: ep for ep in entry_points(group=COMMAND_GROUP)}
    points.update({ep.name: ep for ep in _declared_in(pyproject)})
    commands: dict[str, tuple[str, str]] = {}
    for name, point in sorted(points.items()):
        if name in SUBCOMMANDS:
            log.warning("entry point %s in %s ignored: a built-in command", name, COMMAND_GROUP)
            continue
        try:
            module, help_text = point.load()
        except (ImportError, AttributeError, TypeError, ValueError) as e:
            log.warning("command %r (%s) unavailable: %s", name, point.value, e)
            continue
        commands[name] = (str(module), str(help_text))
    return commands


def commands_for(chosen: str | None) -> dict[str, tuple[str, str]]:
    """The product's subcommands; the plugged-in ones too unless ``chosen`` is the product's."""
    if chosen in SUBCOMMANDS:
        return dict(SUBCOMMANDS)
    return {**SUBCOMMANDS, **plugin_commands()}


def _build_parser(
    chosen: str | None, commands: dict[str, tuple[str, str]]
) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="deepxpalm",
        description="DeepXPalm: feel on the palm what a remote robot's gripper feels.",
    )
    parser.add_argument(
        "-v", "--verbose", action="count", default=0, help="more logging (-vv debug)"
    )
    parser.add_argument(
        "--version", action=_Version, nargs=0, help="print the installed version and exit"
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_text) in commands.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if name == chosen:
            importlib.import_module(module).add_arguments(p)
    return parser


_VERBOSE = re.compile(r"-v+|--verbose")


def _verbosity_after(extra: list[str]) -> tuple[int, list[str]]:
    """``-v`` after the subcommand (``deepxpalm robot -v``, ``keys show K -v``): what no
    command's own parser took; its count, and what else is left (an error, as before)."""
    count, rest = 0, []
    for token in extra:
        if _VERBOSE.fullmatch(token):
            count += 1 if token == "--verbose" else len(token) - 1
        else:
            rest.append(token)
    return count, rest


class _Version(argparse.Action):
    """``--version``: the installed distribution's version, looked up only when asked (the
    metadata's import is no cost of ``deepxpalm palm lift``)."""

    def __call__(self, parser: argparse.ArgumentParser, *args: object) -> None:
        print(f"deepxpalm {package_version()}")
        parser.exit()


def package_version() -> str:
    """The installed version; a checkout run without installing it: its pyproject.toml's."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("deepxpalm")
    except PackageNotFoundError:
        import tomllib

        try:
            return str(tomllib.loads(CHECKOUT_PYPROJECT.read_text())["project"]["version"])
        except (OSError, KeyError, tomllib.TOMLDecodeError):
            return "unknown"


def _dump_stacks_on_request(on_usr1: bool) -> None:
    """``kill -USR1 <pid>`` writes every thread's stack to stderr (the unit's journal).

    The one way to see where a frozen node is stuck without stopping it; a
    crash in a native library (SIGSEGV, SIGABRT) dumps the same. faulthandler
    writes from the signal handler, so it works even while a thread holds the GIL.
    """
    try:
        faulthandler.enable()
        if on_usr1 and hasattr(signal, "SIGUSR1"):
            faulthandler.register(signal.SIGUSR1, all_threads=True)
    except (io.UnsupportedOperation, ValueError):  # stderr is no file (main() called in-process)
        log.debug("no stack dumps: stderr has no file descriptor")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    chosen = next((a for a in argv if not a.startswith("-")), None)
    commands = commands_for(chosen)
    if chosen not in commands:
        chosen = None
    parser = _build_parser(chosen, commands)
    # a command with a -v of its own (`sim ur -v`) takes it; any other -v after the command
    # is the same as one before it
    args, extra = parser.parse_known_args(argv)
    after, rest = _verbosity_after(extra)
    if rest:
        parser.error(f"unrecognized arguments: {' '.join(rest)}")
    if args.command is None:
        parser.print_help()
        return 2
    args.verbose += after  # -v before the command and after it
    configure_logging([logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)])
    _dump_stacks_on_request(args.command != "sim")  # simulators use SIGUSR1 as "unplug"
    module = importlib.import_module(commands[args.command][0])
    try:
        return int(module.run(args) or 0)
    except DeepXPalmError as e:
        # one line, the log's: its priority in the journal, its time and level on a terminal
        logging.getLogger("deepxpalm").error("%s: %s", args.command, e)
        return 2 if isinstance(e, ConfigError) else 1  # 2: what was given is wrong
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
