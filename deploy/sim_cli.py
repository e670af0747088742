"""``deepxpalm sim``: one device simulator on its real wire, standalone.

For bringing up hardware: run the simulator beside the real device and
compare what each says to the same driver, byte for byte.

    deepxpalm sim tactile        # a pty that streams tactile frames at 120 Hz
    deepxpalm sim servos         # a fake Feetech STS bus on a pty
    deepxpalm sim gripper        # the Robotiq URCap socket protocol on TCP
    deepxpalm sim ur             # RTDE 30004, dashboard 29999, script 30003
    deepxpalm sim world          # the simulated lab: an arm, a gripper, the pads, a camera

A simulator with a cable (tactile, servos, gripper) is unplugged by SIGUSR1
and plugged back by SIGUSR2, as a hand pulls and pushes a connector.
``--status-file`` is its front panel: its counters (and the servos' goal
positions) rewritten every 20 ms, for an observer outside every process it
serves (the fault matrix reads the palm this way).
"""

from __future__ import annotations

import argparse
import json
import signal
import threading
import time
from pathlib import Path
from typing import Any

from common.config.typed import from_dict, load_toml
from common.process.command_line import write_stats
from common.process.sd_notify import Notifier
from common.process.signals import on_signal, stop_on_signals

SIMULATORS = {
    "tactile": ("robot_side.tactile.board_sim", "TactileBoardSimulator", "TactileBoardSimConfig"),
    "servos": ("operator_side.servos.sts_sim", "FakeStsBus", "FakeStsBusConfig"),
    "gripper": ("robot_side.gripper.sim", "GripperSimServer", "GripperSimConfig"),
    "ur": ("robot_side.arm.sim.server", "URSimulator", "URSimConfig"),
    # its addresses (with the board's calibration) are what a scene's running_world reads
    "world": ("robot_side.lab.server", "LabServer", "LabWorldConfig"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = __doc__
    parser.add_argument("device", choices=sorted(SIMULATORS))
    parser.add_argument("--config", type=Path, help="TOML with the simulator's settings")
    parser.add_argument("--duration", type=float, help="stop after this many seconds")
    parser.add_argument(
        "--status-file",
        type=Path,
        help="rewrite the simulator's state here every 20 ms (JSON, replaced atomically)",
    )


STATUS_PERIOD_S = 0.02
#: how far back the front panel lists the goals written to the servos: many status periods,
#: so an observer that misses a few panels (a loaded machine) still sees every goal
GOAL_LOG_SPAN_NS = 500_000_000


def front_panel(sim: Any, previous_ns: int | None = None) -> dict[str, Any]:
    """What an observer may read of a running simulator: its counters, the servos' goals.

    The goal and torque-off logs reach back ``GOAL_LOG_SPAN_NS``, and at least to the
    previous panel (``previous_ns``): a panel written late (this process starved) still
    lists every write since the one before it.
    """
    stats = getattr(sim, "stats", None)
    panel: dict[str, Any] = {"t_ns": time.monotonic_ns(), **(stats() if callable(stats) else {})}
    ids = getattr(getattr(sim, "config", None), "ids", None)
    if ids is not None and callable(getattr(sim, "goal", None)):
        panel["goals"] = {str(i): sim.goal(i) for i in ids}
        panel["torque"] = {str(i): sim.torque(i) for i in ids}
    goal_log = getattr(sim, "goal_log", None)
    since = (panel["t_ns"] if previous_ns is None else previous_ns) - GOAL_LOG_SPAN_NS
    if goal_log is not None:  # every goal that reached a servo lately, so a reader misses none
        panel["goal_log"] = [list(entry) for entry in list(goal_log) if entry[0] >= since]
    release_log = getattr(sim, "release_log", None)
    if release_log is not None:  # every torque off lately, and where the servo was let go
        panel["release_log"] = [list(entry) for entry in list(release_log) if entry[0] >= since]
    plugged = getattr(sim, "plugged_in", None)
    if isinstance(plugged, bool):
        panel["plugged_in"] = plugged
    return panel


def _cable_on_signals(sim: Any) -> None:
    """SIGUSR1 unplugs, SIGUSR2 plugs back in, for simulators that have a cable."""
    if callable(getattr(sim, "unplug", None)):
        on_signal(signal.SIGUSR1, sim.unplug)
        on_signal(signal.SIGUSR2, sim.replug)


def _publish_status(sim: Any, path: Path, stop: threading.Event, previous_ns: int) -> None:
    while not stop.wait(STATUS_PERIOD_S):
        panel = front_panel(sim, previous_ns)
        write_stats(path, panel)
        previous_ns = panel["t_ns"]


def _where(sim: Any) -> dict[str, Any]:
    """Where the simulator serves: its port, host or address (a world's every device)."""
    addresses = getattr(sim, "addresses", None)
    if callable(addresses):
        return dict(addresses())
    out = {}
    for name in ("port", "host", "address"):
        value = getattr(sim, name, None)
        if value is not None and not callable(value):
            out[name] = value
    return out


def run(args: argparse.Namespace) -> int:
    import importlib

    from common.devices.lifecycle import SIMULATED_HARDWARE_NICE
    from common.process.realtime import raise_this_thread
    from deploy.units.policy import set_niceness

    # a device never waits for the PC's CPU: where it may, the simulator outranks ordinary work
    set_niceness(SIMULATED_HARDWARE_NICE)
    module_name, cls_name, config_name = SIMULATORS[args.device]
    module = importlib.import_module(module_name)
    # one that stands for hard real-time hardware says so (the UR controller): SCHED_FIFO
    # where granted, for every thread it starts from here on
    priority = getattr(getattr(module, cls_name), "REALTIME_PRIORITY", 0)
    if priority:
        raise_this_thread(priority, SIMULATED_HARDWARE_NICE)
    data = load_toml(args.config) if args.config else {}
    config = from_dict(getattr(module, config_name), data, where=args.device)
    stop = stop_on_signals()
    sim = getattr(module, cls_name)(config)
    sim.start()
    _cable_on_signals(sim)
    if args.status_file is not None:
        first = front_panel(sim)
        write_stats(args.status_file, first)
        threading.Thread(
            target=_publish_status,
            args=(sim, args.status_file, stop, first["t_ns"]),
            daemon=True,
        ).start()
    try:
        where = _where(sim)
        print(json.dumps({"simulator": args.device, **where}), flush=True)
        # systemd, or whoever started it, learns where it serves (a port-0 config's port too)
        Notifier().ready(f"{args.device} simulator", where)
        stop.wait(args.duration)
    finally:
        stop.set()
        sim.stop()
        stats = getattr(sim, "stats", None)
        if callable(stats):
            print(json.dumps({"final": stats()}, default=str), flush=True)
    return 0
