"""The operator node with its dashboard as its own process, as deployed, for browser tests.

``OperatorWithDashboard`` starts ``deepxpalm -v operator`` as its unit (its
priority, its notify socket) on a robot's plain loopback link
(``RobotUnderCommands``), its servos recorded and its dashboard on a port of
its own choosing, which its ``READY=1`` names; the page's token is the one
its config was given, and the node's snapshot is read from its ``--status-file``.
The node's threads then share an interpreter with nothing of the test's (the
browser's driver, the simulators' probes), as on an operator PC: a test that
times a stop through the page times the product, not the test's own process.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from common.web.web_token import new_token, with_token
from common.wire.signing import write_secret_file
from deploy.units.service import Service
from harness.node_logs import LogLine, read_log_lines
from operator_side.dashboard.snapshot import Snapshot

_OPERATOR_TOML = """
[operator.servos]
kind = "in_memory"
[operator.link]
telemetry_endpoint = "{tel}"
command_endpoint = "{cmd}"
[operator.dashboard]
enabled = true
port = 0
token = "{token}"
"""


class OperatorWithDashboard:
    """``deepxpalm operator`` with its dashboard in a process of its own (a context manager).

    ``settings`` are ``--set KEY=VALUE`` overrides on the node's command line.
    """

    def __init__(
        self,
        workdir: Path,
        telemetry_endpoint: str,
        command_endpoint: str,
        settings: tuple[str, ...] = (),
    ) -> None:
        self.workdir = workdir
        self.config = workdir / "operator.toml"
        self.status = workdir / "operator-status.json"
        self.log = workdir / "operator.log"
        #: the page's token: given to the node, as whoever opens its page has it
        self.token = new_token()
        write_secret_file(
            self.config,
            _OPERATOR_TOML.format(tel=telemetry_endpoint, cmd=command_endpoint, token=self.token),
        )
        sets = [a for kv in settings for a in ("--set", kv)]
        argv = ["-v", "operator", "--config", str(self.config)]
        argv += ["--status-file", str(self.status), *sets]
        self.service = Service("operator", argv, self.log, watchdog=False)

    @property
    def proc(self) -> Any:
        return self.service.popen

    def __enter__(self) -> OperatorWithDashboard:
        self.status.unlink(missing_ok=True)
        try:  # at its unit's niceness, as its unit runs it; up once it said where its page is
            base = self.service.up().endpoints["dashboard"]
        except BaseException:
            self.service.close()
            raise
        #: the page's address, its token included (what the operator opens)
        self.url: str = with_token(base, self.token)
        self.port: int = urlsplit(base).port or 80
        return self

    def __exit__(self, *exc: object) -> None:
        self.service.stop(15)
        self.service.close()

    def _status(self) -> dict[str, Any]:
        try:
            return json.loads(self.status.read_text())
        except (FileNotFoundError, json.JSONDecodeError):  # not yet written
            return {}

    def snapshot(self) -> Snapshot:
        """The node's live view and counters (its status file, rewritten every 0.1 s)."""
        return Snapshot.from_json(self._status()["snapshot"])

    def log_lines(self, name: str = "") -> list[LogLine]:
        return read_log_lines(self.log, name)

    def log_tail(self, chars: int = 3000) -> str:
        return self.log.read_text(errors="replace")[-chars:]
