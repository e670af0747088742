"""``deepxpalm video``: stream a camera from the robot PC to the operator's dashboard.

SIGTERM (systemd's stop) and Ctrl-C close every viewer and exit. Should an
encoder thread be stuck in native code, the process exits without joining
it (Python would otherwise wait for it forever at exit, and systemd would
have to SIGKILL a server that had looked as if it ignored SIGTERM). The
interpreter's teardown is skipped after every stop, and a stop held up
past its bound ends the process with every thread's stack in the log; so
does a main thread kept from running for five seconds while it serves.
"""

from __future__ import annotations

import argparse
import faulthandler
import logging
import os
import sys
import threading
import time

from common.process.command_line import (
    add_config_arguments,
    load_node_config,
    print_config,
    stop_on_signals,
    write_stats,
)
from common.process.sd_notify import Notifier
from robot_side.video.server import VideoConfig

log = logging.getLogger(__name__)

STOP_S = 5.0  # VideoServer.stop's bound: viewers closed, threads ended or left
EXIT_GRACE_S = 2.0  # then the stats file and the logs; past that the process is ended
AWAKE_S = 1.0  # the main thread wakes this often while it serves
STALL_S = 5.0  # a main thread that has not woken for this long ends the process, stacks logged


def wait_for_stop(stop: threading.Event, duration_s: float | None) -> None:
    """Until SIGTERM, Ctrl-C or ``duration_s``, waking every ``AWAKE_S`` to re-arm the stall timer.

    The timer runs in C, without the GIL: a main thread kept from running for ``STALL_S``
    (native code holding the GIL, a signal whose wake-up never reached this wait) ends the
    process with every thread's stack in the log, as systemd's SIGKILL would end it with
    nothing said. Waking also runs any signal handler that is due, whichever thread the
    kernel delivered the signal to.
    """
    deadline = None if duration_s is None else time.monotonic() + duration_s
    while True:
        faulthandler.dump_traceback_later(STALL_S, exit=True)
        left = AWAKE_S if deadline is None else min(AWAKE_S, deadline - time.monotonic())
        if left <= 0 or stop.wait(left):
            return


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_config_arguments(parser, VideoConfig, "video", example="source=v4l2")


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
        # systemd (or whoever started it) learns where it serves: a port-0 config's port too
        Notifier().ready(
            f"serving {config.source} at {server.base_url}", {"signalling": server.base_url}
        )
        wait_for_stop(stop, args.duration)
    finally:
        # whatever holds the stop up past its bound, the process ends, its threads' stacks in
        # the log (systemd would SIGKILL it at TimeoutStopSec with nothing said)
        faulthandler.dump_traceback_later(STOP_S + EXIT_GRACE_S, exit=True)
        clean = server.stop(STOP_S)
        write_stats(args.stats_file, server.stats())
    if not clean:
        log.error("video: exiting without waiting for a stuck encoder thread")
    # nothing is left to flush but the logs: the interpreter's own teardown (joining the
    # encoders' worker threads, collecting aiortc's and PyAV's objects) is not waited for
    logging.shutdown()
    sys.stdout.flush()
    os._exit(0 if clean else 1)
