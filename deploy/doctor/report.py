"""The report: one line per check, with its fix, as text or JSON."""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from typing import Any

from common.devices.preflight import FAIL, PASS, SKIP, WARN

log = logging.getLogger(__name__)


ROLES = ("robot", "operator", "router")
#: The user the systemd units run as (deploy/systemd/*.service).
SERVICE_USER = "deepxpalm"
#: What the units add to the service user's groups (SupplementaryGroups=).
SERVICE_GROUPS = ("dialout",)


@dataclass
class Check:
    """One line of the report: what was checked, what was found, and the fix."""

    name: str
    status: str  # pass | warn | fail | skip
    detail: str
    fix: str = ""


@dataclass
class DoctorOptions:
    device_timeout_s: float = 5.0  # connect + status of one device
    peer_timeout_s: float = 3.0  # how long to wait for the other node's heartbeats
    tcp_timeout_s: float = 1.0  # one TCP connect
    connect_devices: bool = True  # False: presence checks only, drivers not opened
    check_peer: bool = True
    service_user: str = SERVICE_USER
    keep_alive_probe_s: float = 2.0  # the real-time probe's length on the robot; 0: skipped


@dataclass
class Report:
    role: str
    source: str
    checks: list[Check] = field(default_factory=list)

    def add(self, name: str, status: str, detail: str, fix: str = "") -> Check:
        check = Check(name, status, detail, fix)
        self.checks.append(check)
        log.debug("%s %s: %s", status, name, detail)
        return check

    @property
    def ok(self) -> bool:
        return not any(c.status == FAIL for c in self.checks)

    def counts(self) -> dict[str, int]:
        return {s: sum(c.status == s for c in self.checks) for s in (PASS, WARN, FAIL, SKIP)}

    def failures(self) -> list[Check]:
        return [c for c in self.checks if c.status == FAIL]

    def find(self, name: str) -> Check:
        """The first check whose name starts with ``name`` (for tests and scripts)."""
        for c in self.checks:
            if c.name.startswith(name):
                return c
        raise KeyError(f"no check named {name!r}; have {[c.name for c in self.checks]}")

    def to_dict(self) -> dict[str, Any]:
        return {
            "role": self.role,
            "config": self.source,
            "ok": self.ok,
            "counts": self.counts(),
            "checks": [dataclasses.asdict(c) for c in self.checks],
        }

    def to_text(self) -> str:
        lines = [f"deepxpalm doctor: {self.role} node, config {self.source}", ""]
        width = max((len(c.name) for c in self.checks), default=10)
        for c in self.checks:
            lines.append(f"  {c.status.upper():<4}  {c.name:<{width}}  {c.detail}")
            if c.fix and c.status in (FAIL, WARN):
                lines.append(f"        {'':<{width}}  fix: {c.fix}")
        n = self.counts()
        verdict = "ready for a session" if self.ok else "NOT ready: fix the failures above"
        lines += [
            "",
            f"{n[FAIL]} failed, {n[WARN]} warnings, {n[PASS]} passed, {n[SKIP]} skipped: {verdict}",
        ]
        return "\n".join(lines)
