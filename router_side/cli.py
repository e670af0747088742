"""``deepxpalm router``: the fabric's Zenoh router, on a host both sites can reach."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from common.config.typed import defaults_toml
from common.process.command_line import (
    add_overrides_argument,
    load_node_config,
    print_config,
    reload_on_hangup,
    stop_on_signals,
    write_stats,
)
from router_side.config import RouterConfig

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = (
        "Configuration: a TOML file with these keys, at the top level or under [router]. "
        "Defaults:\n\n"
        + "\n".join("  " + line for line in defaults_toml(RouterConfig, "router").splitlines())
    )
    parser.add_argument("--config", type=Path, help="TOML config file")
    add_overrides_argument(parser, "router.listen_endpoint=quic/0.0.0.0:7447")
    parser.add_argument(
        "--print-config", action="store_true", help="print the effective config and exit"
    )
    parser.add_argument(
        "--print-zenoh-config",
        action="store_true",
        help="print the Zenoh config made from the roster (ACL, limits) as JSON and exit",
    )
    parser.add_argument("--stats-file", type=Path, help="write final counters here as JSON on exit")
    parser.add_argument("--duration", type=float, help="stop after this many seconds")


def run(args: argparse.Namespace) -> int:
    import json

    from router_side.router import Router

    config = load_node_config(args, RouterConfig, "router")
    if args.print_config:
        print_config(config, "router")
        return 0
    router = Router(config)
    if args.print_zenoh_config:
        print(json.dumps(router.zenoh_config(), indent=2))
        return 0
    stop = stop_on_signals()
    router.start()
    reload_on_hangup(router.roster_reload)
    print(f"router up: {router.endpoint}", flush=True)
    try:
        router.run(stop, args.duration)
    finally:
        write_stats(args.stats_file, router.stats())
    return 0
