"""The ``deepxpalm`` command.

Each subcommand lives in its own module with ``add_arguments(parser)`` and
``run(args) -> int``; only the chosen one is imported, so ``deepxpalm
operator`` never pays for (or depends on) what the robot needs.
"""

from __future__ import annotations

import argparse
import faulthandler
import importlib
import io
import logging
import signal
import sys

from common.errors import DeepXPalmError
from common.logs import configure as configure_logging

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
    "relay": (
        "relay_side.cli",
        "run the relay: robots and operators connect out to it (docs/deploy.md)",
    ),
    "record": ("operator_side.record_cli", "keep every robot's stream from a relay, to a file"),
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
    "bench": ("deploy.bench.cli", "latency budget, run time against error: docs/benchmarks.md"),
    "doctor": ("deploy.doctor", "check this machine before a session: config, devices, keys, peer"),
    "replay": ("deploy.replay", "check a recording against the pipeline, or publish it again"),
    "export": ("deploy.export.cli", "recorded sessions -> a LeRobot dataset (docs/datasets.md)"),
    "soak": ("deploy.soak", "run the demo for a long time on a bad link and report how it aged"),
    "study": ("operator_side.study.cli", "run the palm perception study and analyse it"),
}


def _build_parser(chosen: str | None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="deepxpalm",
        description="DeepXPalm: feel on the palm what a remote robot's gripper feels.",
    )
    parser.add_argument(
        "-v", "--verbose", action="count", default=0, help="more logging (-vv debug)"
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_text) in SUBCOMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if name == chosen:
            importlib.import_module(module).add_arguments(p)
    return parser


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
    if chosen not in SUBCOMMANDS:
        chosen = None
    parser = _build_parser(chosen)
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    configure_logging([logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)])
    _dump_stacks_on_request(args.command != "sim")  # simulators use SIGUSR1 as "unplug"
    module = importlib.import_module(SUBCOMMANDS[args.command][0])
    try:
        return int(module.run(args) or 0)
    except DeepXPalmError as e:
        logging.getLogger("deepxpalm").error("%s", e)
        print(f"deepxpalm {args.command}: error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
