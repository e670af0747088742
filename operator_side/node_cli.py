"""``deepxpalm operator``: run the operator node on the operator's PC."""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import threading
from typing import Any

from common.cli_support import add_config_arguments, run_node
from operator_side.config import OperatorConfig

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_config_arguments(parser, OperatorConfig, "operator")
    parser.add_argument(
        "--commands-from-stdin",
        action="store_true",
        help='read commands as JSON lines on stdin, e.g. {"action": "arm_jog", '
        '"velocity": [0.02, 0, 0, 0, 0, 0]} or {"action": "lease_grant", '
        '"grantee": "HEX"} (scripts and tests drive a real process this way)',
    )


def _build(config: OperatorConfig, recorder: Any) -> Any:
    from operator_side.node import build_operator_node

    return build_operator_node(config, recorder=recorder)


class StdinCommands:
    """JSON lines on stdin -> ``node.send_command``; a bad line is logged and skipped."""

    def __init__(self, node: Any) -> None:
        self.node = node
        self._thread = threading.Thread(target=self._run, name="stdin-commands", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        for line in sys.stdin:
            if not line.strip():
                continue
            try:
                cmd = json.loads(line)
                grantee = cmd.get("grantee")
                velocity = cmd.get("velocity")
                self.node.send_command(
                    cmd["action"],
                    grip_level=cmd.get("grip_level"),
                    velocity=None if velocity is None else tuple(float(v) for v in velocity),
                    grantee=None if grantee is None else bytes.fromhex(grantee),
                )
            except (ValueError, KeyError, TypeError, AttributeError) as e:
                log.warning("stdin command %r skipped: %s", line.strip()[:200], e)

    def stop(self) -> None:
        pass  # a daemon thread blocked on stdin; it ends with the process


def _attachments(node: Any, config: OperatorConfig, from_stdin: bool) -> Any:
    dashboard = _dashboard(node, config)
    if not from_stdin:
        return dashboard
    stdin = StdinCommands(node)
    return stdin if dashboard is None else _Both(dashboard, stdin)


class _Both:
    def __init__(self, *parts: Any) -> None:
        self.parts = parts

    def stop(self) -> None:
        for part in self.parts:
            part.stop()


def _dashboard(node: Any, config: OperatorConfig) -> Any:
    if not config.dashboard.enabled:
        return None
    from operator_side.dashboard import Dashboard  # websockets only when asked for

    dashboard = Dashboard(node, config.dashboard)
    dashboard.start()
    from operator_side.dashboard.config import TOKEN_ENV

    if _stdout_is_journal() and (config.dashboard.token or os.environ.get(TOKEN_ENV)):
        # a token set by whoever may open the page: they have it, the journal need not
        where = "dashboard.token" if config.dashboard.token else f"${TOKEN_ENV}"
        print(f"dashboard: {dashboard.server.base_url} (token: {where})", flush=True)
    else:
        # printed once (the only place a fresh token is shown); no log line carries it
        print(f"dashboard: {dashboard.url}", flush=True)
    return dashboard


def _stdout_is_journal() -> bool:
    """Whether stdout is systemd's journal (``$JOURNAL_STREAM`` names its device:inode)."""
    stream = os.environ.get("JOURNAL_STREAM", "")
    try:
        st = os.fstat(sys.stdout.fileno())
    except (OSError, ValueError):
        return False
    return stream == f"{st.st_dev}:{st.st_ino}"


def run(args: argparse.Namespace) -> int:
    from_stdin = bool(getattr(args, "commands_from_stdin", False))
    return run_node(
        args,
        OperatorConfig,
        "operator",
        _build,
        lambda node, config: _attachments(node, config, from_stdin),
    )
