"""``deepxpalm topic`` through a real router, with a recorder's certificate from its config.

The robot is the product's own ``FabricPublisher`` on cell1's session (QUIC,
mutual TLS) to a router made from the roster; the command reads the way a
recorder does (every message queued, none dropped for a newer one), with the
settings of a recorder's config file: the rates it prints are the rates the
robot sent, and ``echo`` decodes a stimulus signed by the robot's key.
"""

from __future__ import annotations

import argparse
import io
import json
import threading

import pytest
from telemetry_publisher import CELLS, TelemetryPublisher, check_rates

from common.fabric.link import FabricPublisher
from common.wire.signing import Signer
from deploy import topic_cli

pytestmark = [pytest.mark.slow, pytest.mark.timeout(120)]

RATES = {"stimulus": 50.0, "heartbeat": 20.0}


def _topic(*argv: str) -> tuple[int, str, str]:
    parser = argparse.ArgumentParser()
    topic_cli.add_arguments(parser)
    out, err = io.StringIO(), io.StringIO()
    code = topic_cli.watch(parser.parse_args(list(argv)), threading.Event(), out, err)
    return code, out.getvalue(), err.getvalue()


@pytest.fixture
def robot(site):
    signer = Signer.generate()
    pub = FabricPublisher(site.session("cell1"), robot=b"cell1", operator=None, signer=signer)
    with TelemetryPublisher(pub, RATES) as telemetry:
        telemetry.signer = signer
        yield telemetry
    pub.close()


@pytest.fixture
def recorder_config(site, tmp_path):
    config = tmp_path / "recorder.toml"
    config.write_text(
        "[recorder]\n"
        'mode = "fabric"\n'
        'robots = ["cell1"]\n'
        "[recorder.fabric]\n"
        f'router_endpoint = "{site.fleet.router_endpoint}"\n'
        f'cert_dir = "{site.fleet.cert_dir}"\n'
        'name = "rec"\n'
    )
    return config


def test_rates_through_the_router_are_the_rates_the_robot_sent(robot, recorder_config):
    code, out, err = _topic("--config", str(recorder_config), "--duration", "3", "--json")
    assert code == 0, err
    topics = json.loads(out)["robots"]["cell1"]["topics"]
    check_rates(topics, robot)
    for topic in RATES:
        assert topics[topic]["sessions"] == {f"{robot.session:016x}": topics[topic]["count"]}


def test_echo_through_the_router_decodes_a_signed_stimulus(robot, recorder_config, tmp_path):
    key = tmp_path / "cell1.sign"
    key.write_text(robot.signer.public.hex() + "\n")
    code, out, err = _topic(
        *("echo", "--config", str(recorder_config), "--topic", "stimulus"),
        *("--count", "1", "--duration", "20", "--json", "--robot-key", str(key)),
    )
    assert code == 0, err
    record = json.loads(out)
    assert (record["robot"], record["signed"]) == ("cell1", "robot key")
    assert record["fields"]["stimulus"] == CELLS.tolist()


def test_a_robot_the_roster_does_not_name_gives_nothing_and_says_where_to_look(site, tmp_path):
    config = tmp_path / "recorder.toml"
    config.write_text(
        "[recorder]\n"
        'mode = "fabric"\n'
        'robots = ["nobody"]\n'
        "[recorder.fabric]\n"
        f'router_endpoint = "{site.fleet.router_endpoint}"\n'
        f'cert_dir = "{site.fleet.cert_dir}"\n'
        'name = "rec"\n'
    )
    code, _, err = _topic("--config", str(config), "--duration", "1.5")
    assert code == 1
    assert "the router answers" in err and "roster" in err
