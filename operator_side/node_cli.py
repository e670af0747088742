"""``deepxpalm operator``: run the operator node on the operator's PC."""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import sys
import threading
import time
from pathlib import Path
from typing import Any

from common.errors import ConfigError
from common.process.command_line import add_config_arguments, run_node
from operator_side.node.config import OperatorConfig

log = logging.getLogger(__name__)

STATUS_PERIOD_S = 0.1


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_config_arguments(
        parser,
        OperatorConfig,
        "operator",
        example="link.telemetry_endpoint=tcp://192.168.1.20:5555",
        record=True,
    )
    parser.add_argument(
        "--commands-from-stdin",
        action="store_true",
        help='read commands as JSON lines on stdin, e.g. {"action": "arm_jog", '
        '"velocity": [0.02, 0, 0, 0, 0, 0]} or {"action": "lease_grant", '
        '"grantee": "HEX"} (scripts and tests drive a real process this way); an optional '
        '"issued_monotonic_s" (the writer\'s time.monotonic() on this machine) makes a jog '
        "that waited in the pipe longer than link.jog_max_age_ms dropped, as a page's is",
    )
    parser.add_argument(
        "--status-file",
        type=Path,
        help="rewrite what the node shows (its live view, counters, dashboard address) here "
        f"every {STATUS_PERIOD_S * 1e3:.0f} ms, JSON replaced atomically: how `deepxpalm demo` "
        "shows its operator, which runs as a process of its own. The file is 0600: it holds the "
        "dashboard's address with its token, which is then not printed",
    )
    parser.add_argument(
        "--record-metadata",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help=f"with --record: a {SESSION_METADATA} entry in the recording (repeatable), which "
        "`deepxpalm export` puts in a dataset's metadata, e.g. --record-metadata scene=demo",
    )


#: the recording's metadata record that ``--record-metadata`` fills
SESSION_METADATA = "deepxpalm.session"


def session_metadata(pairs: list[str]) -> dict[str, str]:
    """``KEY=VALUE`` strings as a map; a pair without ``=`` or a key is an error to fix."""
    out: dict[str, str] = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"--record-metadata {pair!r}: expected KEY=VALUE, e.g. scene=demo")
        out[key.strip()] = value
    return out


def _build(config: OperatorConfig, recorder: Any, session: dict[str, str]) -> Any:
    from operator_side.node import build_operator_node

    if recorder is not None and session:
        recorder.add_metadata(SESSION_METADATA, session)
    return build_operator_node(config, recorder=recorder)


def _age_ms(issued_monotonic_s: Any) -> float:
    """How long ago a stdin command was written, from the writer's monotonic clock (which every
    process on this machine shares); 0 when it does not say."""
    if issued_monotonic_s is None:
        return 0.0
    issued = float(issued_monotonic_s)
    if not math.isfinite(issued):
        raise ValueError(f"issued_monotonic_s must be a finite number, not {issued_monotonic_s}")
    return max(time.monotonic() - issued, 0.0) * 1e3


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
                    age_ms=_age_ms(cmd.get("issued_monotonic_s")),
                )
            except (ValueError, KeyError, TypeError, AttributeError) as e:
                log.warning("stdin command %r skipped: %s", line.strip()[:200], e)

    def stop(self) -> None:
        pass  # a daemon thread blocked on stdin; it ends with the process


class StatusFile:
    """The node's snapshot, counters and dashboard address, rewritten every ``STATUS_PERIOD_S``
    and once more at the end (with the final counters)."""

    def __init__(self, node: Any, path: Path, dashboard: Any) -> None:
        self.node, self.path = node, path
        self.dashboard_url = None if dashboard is None else dashboard.url
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="status-file", daemon=True)
        self._thread.start()

    def write(self) -> None:
        status = {
            "t_ns": time.monotonic_ns(),
            "snapshot": self.node.snapshot().as_json(),
            "latency_samples": len(self.node.latencies_ms),
            "dashboard_url": self.dashboard_url,
        }
        # 0600 from its creation (the address carries the page's token), then renamed over
        tmp = self.path.with_name(self.path.name + ".tmp")
        tmp.unlink(missing_ok=True)
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
        with os.fdopen(fd, "w") as f:
            json.dump(status, f, sort_keys=True)
        tmp.replace(self.path)

    def _run(self) -> None:
        while not self._stop.wait(STATUS_PERIOD_S):
            try:
                self.write()
            except Exception:  # a view must not end the node
                log.exception("status file %s not written", self.path)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(2)
        self.write()


def _attachments(
    node: Any,
    config: OperatorConfig,
    args: argparse.Namespace,
    from_stdin: bool,
    status: Path | None,
) -> Any:
    dashboard = _dashboard(node, config, status)
    node.frames_consumed = dashboard is not None or status is not None  # their heatmaps
    parts = [p for p in (dashboard, StdinCommands(node) if from_stdin else None) if p is not None]
    if status is not None:
        parts.append(StatusFile(node, status, dashboard))
    if config.palm_guard and config.servos.get("kind") == "feetech":
        # a bus that outlives the node; stopped after the node's run, which closed the bus
        from operator_side.palm.guard import PalmGuard

        parts.append(PalmGuard.start(args.config, args.overrides))
    served = {} if dashboard is None else {"dashboard": dashboard.server.base_url}
    return _Both(*parts, served=served) if parts else None


class _Both:
    def __init__(self, *parts: Any, served: dict[str, str] | None = None) -> None:
        self.parts = parts
        self.served = served or {}

    def endpoints(self) -> dict[str, str]:
        """What the node serves beside its link, for its READY=1: the dashboard's address
        (its token left out: whoever may open the page has it already)."""
        return dict(self.served)

    def stop(self) -> None:
        for part in self.parts:
            part.stop()


def _dashboard(node: Any, config: OperatorConfig, status: Path | None = None) -> Any:
    if not config.dashboard.enabled:
        return None
    from operator_side.dashboard import Dashboard  # websockets only when asked for

    dashboard = Dashboard(node, config.dashboard)
    dashboard.start()
    from operator_side.dashboard.config import TOKEN_ENV

    if status is not None:
        # whoever reads the status file has the address with its token (deepxpalm demo shows
        # it once); the node's output, a log file, does not
        print(f"dashboard: {dashboard.server.base_url} (token: in {status})", flush=True)
    elif _stdout_is_journal() and (config.dashboard.token or os.environ.get(TOKEN_ENV)):
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
    status = getattr(args, "status_file", None)
    session = session_metadata(getattr(args, "record_metadata", []))
    if session and not args.record:
        raise ConfigError("--record-metadata describes a recording: add --record FILE")
    return run_node(
        args,
        OperatorConfig,
        "operator",
        lambda config, recorder: _build(config, recorder, session),
        lambda node, config: _attachments(node, config, args, from_stdin, status),
    )
