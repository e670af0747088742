"""``deepxpalm operator``: run the operator node on the operator's PC."""

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
from operator_side.config import OperatorConfig


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_config_arguments(parser, OperatorConfig, "operator")
    parser.add_argument("--duration", type=float, help="stop after this many seconds")
    parser.add_argument(
        "--record", type=Path, metavar="FILE", help="record the session to this MCAP file"
    )


def run(args: argparse.Namespace) -> int:
    config = load_node_config(args, OperatorConfig, "operator")
    if args.print_config:
        print_config(config, "operator")
        return 0
    from operator_side.node import build_operator_node

    recorder = None
    if args.record:
        from common.mcap_recorder import node_recorder  # mcap is imported only when recording

        recorder = node_recorder(args.record, config, "operator")
    stop = stop_on_signals()
    try:
        node = build_operator_node(config, recorder=recorder)
        dashboard = None
        if config.dashboard.enabled:
            from operator_side.dashboard import Dashboard  # websockets only when asked for

            dashboard = Dashboard(node, config.dashboard)
            dashboard.start()
            print(f"dashboard: {dashboard.url}", flush=True)
        try:
            node.run(stop, args.duration)
        finally:
            if dashboard is not None:
                dashboard.stop()
            write_stats(args.stats_file, node.stats())
    finally:
        if recorder is not None:
            recorder.close()
    return 0
