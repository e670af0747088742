"""The operator node with its dashboard as its own process, as deployed, for browser tests.

``OperatorWithDashboard`` starts ``deepxpalm -v operator`` at its unit's
priority on a robot's plain loopback link (``RobotUnderCommands``), its servos
recorded and its dashboard on a port of its own choosing, and reads the page's
address (token included) and the node's snapshot from its ``--status-file``.
The node's threads then share an interpreter with nothing of the test's (the
browser's driver, the simulators' probes), as on an operator PC: a test that
times a stop through the page times the product, not the test's own process.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit

from common.signing import write_secret_file
from common.web_token import TOKEN_PARAM
from harness.bench.command_path import LogLine, read_log_lines
from harness.processes import spawn_cli, stop
from operator_side.node.snapshot import Snapshot

_OPERATOR_TOML = """
[operator.servos]
kind = "recording"
[operator.link]
telemetry_endpoint = "{tel}"
command_endpoint = "{cmd}"
[operator.dashboard]
enabled = true
port = 0
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
        write_secret_file(
            self.config, _OPERATOR_TOML.format(tel=telemetry_endpoint, cmd=command_endpoint)
        )
        self.settings = settings

    def __enter__(self) -> OperatorWithDashboard:
        self.status.unlink(missing_ok=True)
        with self.log.open("a") as out:  # at its unit's niceness, as its unit runs it
            sets = [a for kv in self.settings for a in ("--set", kv)]
            argv = ["-v", "operator", "--config", str(self.config)]
            argv += ["--status-file", str(self.status), *sets]
            self.proc = spawn_cli(argv, out, unit="operator")
        deadline = time.monotonic() + 60
        while (url := self._status().get("dashboard_url")) is None:
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.__exit__()
                raise RuntimeError(f"the operator's dashboard never came up:\n{self.log_tail()}")
            time.sleep(0.05)
        #: the page's address, its token included (what the operator opens)
        self.url: str = url
        parts = urlsplit(url)
        self.port: int = parts.port or 80
        self.token: str = parse_qs(parts.query)[TOKEN_PARAM][0]
        return self

    def __exit__(self, *exc: object) -> None:
        stop(self.proc, 15)

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
