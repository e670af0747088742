"""Serve a simulated lab: ``python -m robot_side.lab`` (``--stdio`` for a parent process).

Prints where the UR controller, the Robotiq URCap and the tactile board's
pty are; point ur-rtde, the socket driver and the serial driver at them.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from common.config.typed import from_dict, load_toml
from common.logs import configure as configure_logging
from common.process.sd_notify import Notifier
from common.process.signals import stop_on_signals
from robot_side.lab.config import LabWorldConfig


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m robot_side.lab", description=__doc__)
    ap.add_argument("--stdio", action="store_true", help="take requests as JSON lines on stdin")
    ap.add_argument("--config-json", help="the whole LabWorldConfig as JSON")
    ap.add_argument(
        "--config", type=Path, help="a LabWorldConfig TOML file (a scene's world_config)"
    )
    ap.add_argument("--log-level", type=int, default=logging.INFO)
    ap.add_argument(
        "--addresses-file",
        type=Path,
        help="also write the addresses (with the board's calibration) here, for running_world",
    )
    args = ap.parse_args(argv)
    configure_logging(args.log_level, "%(asctime)s lab %(name)s: %(message)s")
    if args.config_json:
        config = from_dict(LabWorldConfig, json.loads(args.config_json), where="world")
    elif args.config is not None:
        config = from_dict(LabWorldConfig, load_toml(args.config), where=str(args.config))
    else:
        config = LabWorldConfig()
    from robot_side.lab.server import LabServer

    try:
        server = LabServer(config).start()
    except Exception as e:
        if args.stdio:
            print(json.dumps({"error": f"{type(e).__name__}: {e}"}), flush=True)
        raise SystemExit(f"lab: {e}") from None
    if args.stdio:
        from robot_side.lab.process import serve_stdio

        serve_stdio(server, sys.stdin, sys.stdout)
        return
    if args.addresses_file is not None:  # whole or not at all: a reader polls for it
        partial = args.addresses_file.with_suffix(".partial")
        partial.write_text(json.dumps(server.addresses()))
        partial.replace(args.addresses_file)
    done = stop_on_signals()
    print(
        json.dumps(
            {
                k: v
                for k, v in server.addresses().items()
                if "tactile_" not in k or k == "tactile_port"
            }
        ),
        flush=True,
    )
    # systemd, or whoever started it, learns where each simulator listens
    Notifier().ready("the lab world", server.addresses())
    done.wait()
    server.stop()


if __name__ == "__main__":
    main()
