"""``deepxpalm video``: stream a camera from the robot PC to the operator's dashboard.

SIGTERM (systemd's stop) and Ctrl-C close every viewer and exit. Should an
encoder thread be stuck in native code, the process exits without joining
it (Python would otherwise wait for it forever at exit, and systemd would
have to SIGKILL a server that had looked as if it ignored SIGTERM).
"""

from __future__ import annotations

import argparse
import logging
import os

from common.cli_support import (
    add_config_arguments,
    load_node_config,
    print_config,
    stop_on_signals,
    write_stats,
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
    server = VideoServer(build_source(config), config).start()
    try:
        if config.token_file is None:  # this run's secret: the URL is how a viewer gets it
            print(f"video: {server.url} (source {config.source})", flush=True)
        else:
            shown = f"{server.base_url} (token in {config.token_file}, source {config.source})"
            print(f"video: {shown}", flush=True)
        stop.wait(args.duration)
    finally:
        clean = server.stop()
        write_stats(args.stats_file, server.stats())
    if not clean:
        log.error("video: exiting without waiting for a stuck encoder thread")
        logging.shutdown()
        os._exit(1)
    return 0
