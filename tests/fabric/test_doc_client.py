"""A client written from docs/fabric.md alone reads one named robot through a real router.

Plain ``zenoh`` with the settings docs/fabric.md ("A client of your own")
lists, the recorder's certificate, and ``common.wire.codec`` to read each payload
as docs/protocol.md frames it. Two robots, ``cell1`` and ``cell10``, as real
processes: the client reads cell1's stimuli and heartbeats and nothing of
cell10's.
"""

from __future__ import annotations

import json
import time

import pytest
from fleet_monitor import Monitor

from common.clocks.clock import now_ns
from common.wire.codec import decode_named
from common.wire.messages import Heartbeat, Stimulus
from harness.fleet import Fleet

pytestmark = [pytest.mark.slow, pytest.mark.timeout(120)]

#: how many of each kind the client reads (stimuli 60 a second, heartbeats 40)
WANTED = 30


def _client_config(fleet: Fleet, member: str) -> dict:
    """docs/fabric.md's table, for ``member``'s certificate."""
    return {
        "mode": "client",
        "connect": {"endpoints": [f"{fleet.router_endpoint}?mixed_rel=1"]},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {
            "link": {
                "tls": {
                    "root_ca_certificate": str(fleet.cert_dir / "ca.crt"),
                    "connect_certificate": str(fleet.cert_dir / f"{member}.crt"),
                    "connect_private_key": str(fleet.cert_dir / f"{member}.key"),
                    "enable_mtls": True,
                    "verify_name_on_connect": True,
                }
            }
        },
    }


def _read(fleet: Fleet, got: dict[str, list]) -> None:
    """The client: docs/fabric.md's settings, exact keys, until it has ``WANTED`` of each."""
    import zenoh

    config = zenoh.Config.from_json5(json.dumps(_client_config(fleet, "rec")))
    with zenoh.open(config) as session:
        subs = {kind: session.declare_subscriber(f"dxp/cell1/{kind}") for kind in got}
        deadline = time.monotonic() + 60
        while min(len(v) for v in got.values()) < WANTED and time.monotonic() < deadline:
            idle = True
            for kind, sub in subs.items():
                sample = sub.try_recv()
                if sample is not None:
                    idle = False
                    got[kind].append((str(sample.key_expr), sample.payload.to_bytes()))
            if idle:
                time.sleep(0.01)
        for sub in subs.values():
            sub.undeclare()


def test_a_client_written_from_the_fabric_doc_reads_one_named_robot_through_the_router(
    tmp_path,
):
    fleet = Fleet(robots=["cell1", "cell10"], operators={"rec": "recorder"}, workdir=tmp_path)
    got: dict[str, list] = {"stimulus": [], "heartbeat": []}
    with fleet:
        fleet.start_router()
        fleet.start_robot("cell1", None)
        fleet.start_robot("cell10", None)
        # the test's own reader of cell10 (not the doc's client): cell10 streams meanwhile
        cell10 = Monitor(fleet, "rec", ["cell10"])
        try:
            fleet.wait_for(lambda: cell10.stimulus_times, 60, "cell10's stimuli")
            t0 = now_ns()
            _read(fleet, got)
            t1 = now_ns()
        finally:
            cell10.close()
    assert all(len(v) >= WANTED for v in got.values()), {k: len(v) for k, v in got.items()}
    assert any(t0 <= t <= t1 for t in cell10.stimulus_times), "cell10 streamed meanwhile"
    robot_key = fleet.signing_key("cell1")
    for kind, cls in (("stimulus", Stimulus), ("heartbeat", Heartbeat)):
        for key, data in got[kind]:
            assert key == f"dxp/cell1/{kind}"
            # the frame docs/protocol.md describes: topic, length byte, name, map, signature
            assert data[: 4 + 1 + len(b"cell1")] == cls.TOPIC + b"\x05cell1"
            name, msg = decode_named(data)  # its signature verified
            assert name == b"cell1" and isinstance(msg, cls), (name, msg)
            assert msg.signer == robot_key, "signed by cell1's own key"
    stimuli = [decode_named(d)[1] for _, d in got["stimulus"]]
    assert all(len(s.stimulus.ravel()) == 9 for s in stimuli)
    assert any(decode_named(d)[1].node == "robot" for _, d in got["heartbeat"])
