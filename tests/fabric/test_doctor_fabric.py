"""``deepxpalm doctor`` on a node of the fabric: its certificate, the router, its robot."""

from __future__ import annotations

import pytest

from common.devices.preflight import FAIL, PASS, SKIP, WARN
from deploy.doctor.cli import diagnose
from deploy.doctor.report import DoctorOptions

pytestmark = [pytest.mark.slow, pytest.mark.untimed]

OPTIONS = DoctorOptions(peer_timeout_s=1.0, check_peer=True, keep_alive_probe_s=0.1)


def _operator(site, **fabric) -> dict:
    keys = site.fleet.workdir / "keys"
    return {
        "servos": {"kind": "in_memory"},
        "link": {
            "mode": "fabric",
            "robot_name": "cell1",
            "signing_key_file": str(keys / "alice.sign_secret"),
            "robot_key_file": str(keys / "robot-cell1.sign"),
            "fabric": {
                "router_endpoint": site.fleet.router_endpoint,
                "cert_dir": str(site.fleet.cert_dir),
                "name": "alice",
                **fabric,
            },
        },
    }


def _status(report) -> dict[str, str]:
    return {c.name: c.status for c in report.checks}


def test_a_member_the_router_admits_passes_and_a_silent_robot_is_a_warning(site):
    status = _status(diagnose("operator", _operator(site), "test", OPTIONS))
    assert status["fabric: certificate"] == PASS
    assert status["fabric: router"] == PASS
    assert status["fabric: robot"] == WARN  # no robot node runs in this module


def test_a_certificate_of_another_name_fails_and_says_what_to_run(site):
    report = diagnose("operator", _operator(site, name="nobody"), "test", OPTIONS)
    check = next(c for c in report.checks if c.name == "fabric: certificate")
    assert check.status == FAIL and "keys certs" in check.fix
    assert _status(report)["fabric: router"] == SKIP


def test_no_router_at_the_address_fails(site):
    from common.wire.transport import free_loopback_ports

    elsewhere = f"quic/127.0.0.1:{free_loopback_ports(1, udp=True)[0]}"
    report = diagnose("operator", _operator(site, router_endpoint=elsewhere), "test", OPTIONS)
    check = next(c for c in report.checks if c.name == "fabric: router")
    assert check.status == FAIL and "deepxpalm router" in check.fix
