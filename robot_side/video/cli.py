"""``deepxpalm video``: stream a camera from the robot PC to the operator's dashboard."""

from __future__ import annotations

import argparse
import logging

from common.cli_support import (
    add_config_arguments,
    load_node_config,
    print_config,
    stop_on_signals,
)
from robot_side.video.server import VideoConfig

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_config_arguments(parser, VideoConfig, "video")


def run(args: argparse.Namespace) -> int:
    config = load_node_config(args, VideoConfig, "video")
    if args.print_config:
        print_config(config, "video")
        return 0
    from robot_side.video.server import VideoServer, build_source  # aiortc: only to serve

    stop = stop_on_signals()
    with VideoServer(build_source(config), config) as server:
        print(f"video: {server.url} (source {config.source})", flush=True)
        stop.wait(args.duration)
    return 0
