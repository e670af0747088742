"""``deepxpalm robot``: run the robot node on the robot PC."""

from __future__ import annotations

import argparse
from pathlib import Path

from common.cli_support import (
    add_config_arguments,
    load_node_config,
    print_config,
    stop_on_signals,
    write_stats,
)
from robot_side.config import RobotConfig


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_config_arguments(parser, RobotConfig, "robot")
    parser.add_argument("--duration", type=float, help="stop after this many seconds")
    parser.add_argument(
        "--record", type=Path, metavar="FILE", help="record the session to this MCAP file"
    )


def run(args: argparse.Namespace) -> int:
    config = load_node_config(args, RobotConfig, "robot")
    if args.print_config:
        print_config(config, "robot")
        return 0
    from robot_side.node import build_robot_node

    recorder = None
    if args.record:
        from common.mcap_recorder import node_recorder  # mcap is imported only when recording

        recorder = node_recorder(args.record, config, "robot")
    stop = stop_on_signals()
    try:
        node = build_robot_node(config, recorder=recorder)
        try:
            node.run(stop, args.duration)
        finally:
            write_stats(args.stats_file, node.stats())
    finally:
        if recorder is not None:
            recorder.close()
    return 0
