"""A real router in the test process, its roster and certificates made as a deployment's are."""

from __future__ import annotations

import contextlib

import pytest

from common.fabric.session import FabricConfig, cert_files, client_config, open_session
from harness.fleet import Fleet
from router_side.config import RouterConfig
from router_side.router import Router

ROBOTS = ["cell1", "cell2"]
OPERATORS = {"alice": "controller", "olga": "observer", "mallory": "observer", "rec": "recorder"}


class Site:
    """The router and a way to open any member's session to it."""

    def __init__(self, fleet: Fleet, router: Router) -> None:
        self.fleet = fleet
        self.router = router
        self._sessions: list = []

    def session(self, member: str):
        fabric = FabricConfig(router_endpoint=self.fleet.router_endpoint, retry_ms=50.0)
        files = cert_files(self.fleet.cert_dir, member, "test")
        session = open_session(client_config(fabric, files, "test"), member)
        self._sessions.append(session)
        return session

    def close(self) -> None:
        for session in self._sessions:
            with contextlib.suppress(Exception):
                session.close()


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    fleet = Fleet(
        robots=list(ROBOTS),
        operators=dict(OPERATORS),
        workdir=tmp_path_factory.mktemp("fabric"),
    )
    config = RouterConfig(
        listen_endpoint="quic/127.0.0.1:0", roster_file=fleet.roster, cert_dir=fleet.cert_dir
    )
    router = Router(config).start()  # on a free port of its own choosing
    fleet.router_endpoint = router.endpoint
    site = Site(fleet, router)
    try:
        yield site
    finally:
        site.close()
        router.close()
