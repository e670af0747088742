"""``deepxpalm relay``: run the relay on a host that both sites can reach."""

from __future__ import annotations

import argparse
import logging

from common.cli_support import (
    add_config_arguments,
    load_node_config,
    print_config,
    reload_on_hangup,
    stop_on_signals,
    write_stats,
)
from relay_side.config import RelayConfig

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_config_arguments(parser, RelayConfig, "relay")


def run(args: argparse.Namespace) -> int:
    from relay_side.relay import Relay

    config = load_node_config(args, RelayConfig, "relay")
    if args.print_config:
        print_config(config, "relay")
        return 0
    stop = stop_on_signals()
    relay = Relay(config).start()
    reload_on_hangup(relay.roster_reload)
    print("relay up: " + " ".join(f"{k}={v}" for k, v in relay.endpoints.items()), flush=True)
    try:
        relay.run(stop, args.duration)
    finally:
        write_stats(args.stats_file, relay.last_stats)
    return 0
