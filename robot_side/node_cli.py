"""``deepxpalm robot``: run the robot node on the robot PC."""

from __future__ import annotations

import argparse

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


def run(args: argparse.Namespace) -> int:
    config = load_node_config(args, RobotConfig, "robot")
    if args.print_config:
        print_config(config, "robot")
        return 0
    from robot_side.node import build_robot_node

    stop = stop_on_signals()
    node = build_robot_node(config)
    try:
        node.run(stop, args.duration)
    finally:
        write_stats(args.stats_file, node.stats())
    return 0
