"""``deepxpalm view``: a robot's link and a session's recordings, live in Foxglove.

One Foxglove WebSocket server (``common/live_view/server.py``, the
``foxglove`` extra), on loopback and port 8767 unless told otherwise (the
dashboard has 8765, the study's answer page 8766), fed by either or both of:

- **the link** (``deploy/wire_tap.py``, as ``deepxpalm topic`` reads it: a
  robot's direct link with our CURVE keys, or the fabric's router with our
  certificate): the pads (``robot/pads/finger_1``, ``finger_2``), the palm
  (``robot/palm``), the stimulus (``robot/stimulus``), the heartbeat's state
  and counters (``robot/link``) and the arm's pose (``robot/tf/tcp``) as they
  arrive; from anywhere the link reaches;
- **a session's recordings** (``--follow DIR``, on the robot PC: the robot
  node's ``robot.mcap``, the video server's ``camera.mcap``): the camera, the
  arm and the gripper's fingers, the log lines, 1.5 s behind (the recorders
  write a chunk a second; docs/recording.md, "A live view"). A topic the link
  serves is not served again from the files.

In Foxglove: Open connection, Foxglove WebSocket, the address it prints. The
server has no authentication and cannot check a browser's origin
(docs/security.md, "The live view"): a host that is not loopback needs
``--allow-remote``; from another machine, an SSH tunnel.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path
from typing import Any, TextIO

from common.process.command_line import write_stats
from common.recording.foxglove import VIEW_PORT, FoxgloveLiveConfig
from deploy.wire_tap import add_link_arguments, tap_config

EPILOG = f"""\
One Foxglove WebSocket server, on 127.0.0.1:{VIEW_PORT} unless told otherwise (the
dashboard has 8765, the study's answer page 8766), fed by either or both of:
  the link        a robot's, read with your keys as `deepxpalm topic` reads it: the
                  pads, the palm, the stimulus, the heartbeat (robot/link) and the
                  arm's pose (robot/tf/tcp), as they arrive
  --follow DIR    a session being recorded on this PC (the robot node's and the video
                  server's files): the camera, the arm, the fingers, the log, 1.5 s
                  behind; a topic the link serves is not served again from the files
In Foxglove: Open connection, Foxglove WebSocket, the address printed at start. The
server has no authentication and cannot check a browser's origin: keep it on loopback
and tunnel to it (docs/security.md, "The live view").
"""
#: the link's topics the view reads (a robot's video answers are not shown)
WIRE_TOPICS = ("stimulus", "frame", "heartbeat")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = EPILOG
    g = parser.add_argument_group("the view")
    g.add_argument(
        "--host", default="127.0.0.1", help="address to serve on (default: loopback only)"
    )
    g.add_argument(
        "--port", type=int, default=VIEW_PORT, help=f"port (default {VIEW_PORT}; 0: any free)"
    )
    g.add_argument(
        "--allow-remote",
        action="store_true",
        help="serve on a host that is not loopback: anyone who reaches it sees the session",
    )
    g.add_argument(
        "--follow",
        type=Path,
        metavar="DIR",
        help="also serve the session being recorded in DIR (camera, arm, logs); alone, the "
        "link is read only if a flag or --config names it",
    )
    g.add_argument(
        "--delay",
        type=float,
        default=FoxgloveLiveConfig().delay_s,
        help="--follow: send each recorded message this long after its time, s",
    )
    g.add_argument("--duration", type=float, help="stop after this many seconds")
    g.add_argument("--stats-file", type=Path, help="write what was served here as JSON on exit")
    add_link_arguments(parser)


def wants_link(args: argparse.Namespace) -> bool:
    """The link is read unless the view only follows files (no flag names a link)."""
    named = (args.config, args.endpoint, args.router, args.cert_dir, args.robot)
    return args.follow is None or any(named)


class View:
    """The server and its sources; ``step`` moves what arrived to Foxglove."""

    def __init__(self, args: argparse.Namespace, *, ctx: Any = None) -> None:
        from common.live_view.server import WIRE_TOPICS as SERVED_BY_LINK
        from common.live_view.server import LiveServer, WireView

        self.config = FoxgloveLiveConfig(
            follow=args.follow,
            host=args.host,
            port=args.port,
            delay_s=args.delay,
            allow_remote=args.allow_remote,
        )
        self.tap = self.wire = self.files = None
        self.server = LiveServer(self.config)
        try:
            if wants_link(args):
                from deploy.wire_tap import WireTap

                cfg = tap_config(args)
                self.tap = WireTap(cfg, WIRE_TOPICS, ctx=ctx)
                self.wire = WireView(self.server, prefix_robots=len(cfg.robots) > 1)
            if args.follow is not None:
                from common.live_view.session_files import LiveSource

                skip = SERVED_BY_LINK if self.tap is not None else frozenset()
                self.files = LiveSource(self.config, server=self.server, skip_topics=skip)
        except BaseException:
            self.close()
            raise

    @property
    def url(self) -> str:
        return self.server.url

    def describe(self) -> str:
        sources = []
        if self.tap is not None:
            sources.append(f"the link at {self.tap.connection()['via']}")
        if self.files is not None:
            sources.append(f"the recordings in {self.config.follow}")
        return (
            f"Foxglove: open {self.url} (Open connection, Foxglove WebSocket); serving "
            + " and ".join(sources)
        )

    def step(self, timeout_s: float) -> None:
        """Wait up to ``timeout_s`` for the link (or the files' next message) and serve it."""
        if self.files is not None:
            timeout_s = min(timeout_s, self.files.wait_s())
        if self.tap is not None:
            for got in self.tap.read(timeout_s):
                self.wire.take(got.robot, got.msg, got.t_recv_ns)
        else:
            time.sleep(timeout_s)
        if self.files is not None:
            self.files.step()

    def run(self, stop: threading.Event, duration_s: float | None = None) -> None:
        t_end = None if duration_s is None else time.monotonic() + duration_s
        while not stop.is_set() and (t_end is None or time.monotonic() < t_end):
            self.step(0.05)

    def stats(self) -> dict[str, float]:
        out: dict[str, float] = {}
        if self.wire is not None:
            out.update({f"link_{k}": float(v) for k, v in self.wire.counters.items()})
            out.update({f"link_rejected_{k}": float(v) for k, v in self.tap.rejected.items()})
        if self.files is not None:
            out.update({f"foxglove_{k}": float(v) for k, v in self.files.counters.items()})
        return out

    def close(self) -> None:
        if self.tap is not None:
            self.tap.close()
        if self.files is not None:
            self.files.close()
        self.server.close()


def run(args: argparse.Namespace, out: TextIO = sys.stdout) -> int:
    from common.process.signals import stop_on_signals

    stop = stop_on_signals()
    view = View(args)
    try:
        print(view.describe(), file=out, flush=True)
        view.run(stop, args.duration)
    finally:
        write_stats(args.stats_file, view.stats())
        view.close()
    return 0
