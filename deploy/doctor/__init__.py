"""``deepxpalm doctor``: is this machine ready for a session? (``cli`` says how it works.)

One module per concern: ``report`` (the pass/warn/fail lines), ``node_config``,
``keys``, ``devices`` (each device's own preflight, then its driver), ``link``
(ports, the peer's heartbeats, the clock), ``system`` (governor, real time,
service user) and ``cli`` (the command, and ``diagnose`` that runs them all).
"""

from deploy.doctor.cli import add_arguments, diagnose, run
from deploy.doctor.exchange import heartbeat_exchange
from deploy.doctor.node_config import infer_role, node_section
from deploy.doctor.report import FAIL, PASS, SKIP, WARN, Check, DoctorOptions, Report

__all__ = [
    "FAIL",
    "PASS",
    "SKIP",
    "WARN",
    "Check",
    "DoctorOptions",
    "Report",
    "add_arguments",
    "diagnose",
    "heartbeat_exchange",
    "infer_role",
    "node_section",
    "run",
]
