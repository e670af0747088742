"""``deepxpalm sim``: one device simulator on its real wire, standalone.

For bringing up hardware: run the simulator beside the real device and
compare what each says to the same driver, byte for byte.

    deepxpalm sim tactile        # a pty that streams tactile frames at 120 Hz
    deepxpalm sim servos         # a fake Feetech STS bus on a pty
    deepxpalm sim gripper        # the Robotiq URCap socket protocol on TCP
    deepxpalm sim ur             # RTDE 30004, dashboard 29999, script 30003
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from common.cli_support import stop_on_signals
from common.config import from_dict, load_toml

SIMULATORS = {
    "tactile": ("robot_side.tactile.board_sim", "TactileBoardSimulator", "TactileBoardSimConfig"),
    "servos": ("operator_side.servos.sts_sim", "FakeStsBus", "FakeStsBusConfig"),
    "gripper": ("robot_side.gripper.sim", "GripperSimServer", "GripperSimConfig"),
    "ur": ("robot_side.arm.sim.server", "URSimulator", "URSimConfig"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = __doc__
    parser.add_argument("device", choices=sorted(SIMULATORS))
    parser.add_argument("--config", type=Path, help="TOML with the simulator's settings")
    parser.add_argument("--duration", type=float, help="stop after this many seconds")


def _where(sim: Any) -> dict[str, Any]:
    out = {}
    for name in ("port", "host", "address"):
        value = getattr(sim, name, None)
        if value is not None and not callable(value):
            out[name] = value
    return out


def run(args: argparse.Namespace) -> int:
    import importlib

    module_name, cls_name, config_name = SIMULATORS[args.device]
    module = importlib.import_module(module_name)
    data = load_toml(args.config) if args.config else {}
    config = from_dict(getattr(module, config_name), data, where=args.device)
    stop = stop_on_signals()
    sim = getattr(module, cls_name)(config)
    sim.start()
    try:
        print(json.dumps({"simulator": args.device, **_where(sim)}), flush=True)
        stop.wait(args.duration)
    finally:
        sim.stop()
        stats = getattr(sim, "stats", None)
        if callable(stats):
            print(json.dumps({"final": stats()}, default=str), flush=True)
    return 0
