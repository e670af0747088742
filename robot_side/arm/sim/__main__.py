"""Serve a simulated UR controller: ``python -m robot_side.arm.sim --host 127.0.0.2``.

Point ur-rtde at the printed address to compare what it sends with a real
controller; ``-v`` logs every message but the periodic data packages.
``--stdio`` is how :class:`~robot_side.arm.sim.process.URSimProcess` drives
it as a child process.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys

from common.config.typed import from_dict
from common.devices.lifecycle import SIMULATED_HARDWARE_NICE
from common.logs import configure as configure_logging
from common.process.realtime import raise_this_thread
from common.process.signals import stop_on_signals
from robot_side.arm.sim.server import URSimConfig, URSimulator


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m robot_side.arm.sim", description=__doc__)
    ap.add_argument("--host", default="auto", help="loopback address, or 'auto' for a free one")
    ap.add_argument("--tick-hz", type=float, default=500.0)
    ap.add_argument("-v", "--verbose", action="store_true", help="log every message (not data)")
    ap.add_argument("--stdio", action="store_true", help="take requests as JSON lines on stdin")
    ap.add_argument("--config-json", help="the whole URSimConfig as JSON (overrides the above)")
    ap.add_argument("--log-level", type=int, default=None)
    args = ap.parse_args(argv)
    level = (
        args.log_level
        if args.log_level is not None
        else (logging.DEBUG if args.verbose else logging.INFO)
    )
    configure_logging(level, "%(asctime)s ursim %(name)s: %(message)s")
    # before any thread starts: each inherits it
    raise_this_thread(URSimulator.REALTIME_PRIORITY, SIMULATED_HARDWARE_NICE)
    if args.config_json:
        config = from_dict(URSimConfig, json.loads(args.config_json), where="sim")
    else:
        config = URSimConfig(host=args.host, tick_hz=args.tick_hz)
    try:
        sim = URSimulator(config).start()
    except Exception as e:
        if args.stdio:
            print(json.dumps({"error": str(e)}), flush=True)
        raise SystemExit(f"UR simulator: {e}") from None
    if args.stdio:
        from robot_side.arm.sim.process import serve_stdio

        serve_stdio(sim, sys.stdin, sys.stdout)
        return
    done = stop_on_signals()
    logging.getLogger(__name__).info("serving on %s; Ctrl-C to stop", sim.host)
    done.wait()
    sim.stop()


if __name__ == "__main__":
    main()
