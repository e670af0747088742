"""``deepxpalm operator``: run the operator node on the operator's PC."""

from __future__ import annotations

import argparse
from typing import Any

from common.cli_support import add_config_arguments, run_node
from operator_side.config import OperatorConfig


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_config_arguments(parser, OperatorConfig, "operator")


def _build(config: OperatorConfig, recorder: Any) -> Any:
    from operator_side.node import build_operator_node

    return build_operator_node(config, recorder=recorder)


def _dashboard(node: Any, config: OperatorConfig) -> Any:
    if not config.dashboard.enabled:
        return None
    from operator_side.dashboard import Dashboard  # websockets only when asked for

    dashboard = Dashboard(node, config.dashboard)
    dashboard.start()
    print(f"dashboard: {dashboard.url}", flush=True)
    return dashboard


def run(args: argparse.Namespace) -> int:
    return run_node(args, OperatorConfig, "operator", _build, _dashboard)
