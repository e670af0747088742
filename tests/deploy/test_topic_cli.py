"""``deepxpalm topic``: a robot's telemetry read off a real link, with the user's keys.

A ``TelemetryPublisher`` stands in for the robot on a bound ZeroMQ PUB (plain
on loopback, or a CURVE server with an allowlist, as the robot's telemetry
socket is); the command reads it as it reads a robot: its rates match what
was sent, ``echo`` decodes a stimulus and names its signer, ``list`` shows the
session and the refusals the heartbeat reports, and a key the robot does not
allow reads nothing and is told why. A real robot node last.
"""

from __future__ import annotations

import argparse
import io
import json
import subprocess
import sys
import threading

import pytest
from deploy_support import ENV, REPO, cli, loopback
from telemetry_publisher import CELLS, TelemetryPublisher, check_rates
from tests_support import free_ports

from common.keys.curve import Authenticator, SecurityConfig, server_options
from common.wire.signing import Signer
from common.wire.transport import Publisher, Subscriber
from deploy import topic_cli

pytestmark = pytest.mark.slow

RATES = {"stimulus": 50.0, "heartbeat": 20.0, "frame": 10.0}


def _args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    topic_cli.add_arguments(parser)
    return parser.parse_args(list(argv))


def _topic(*argv: str) -> tuple[int, str, str]:
    """(exit code, stdout, stderr) of ``deepxpalm topic ARGV``, in this process."""
    out, err = io.StringIO(), io.StringIO()
    code = topic_cli.watch(_args(*argv), threading.Event(), out, err)
    return code, out.getvalue(), err.getvalue()


@pytest.fixture
def robot(zmq_ctx):
    """A robot named cell1 on a plain loopback PUB, signing what it sends."""
    signer = Signer.generate()
    pub = Publisher(zmq_ctx, "tcp://127.0.0.1:*", bind=True, name=b"cell1", signer=signer)
    refusals = {"n": 0}

    def stats() -> dict[str, float]:
        refusals["n"] += 1
        return {"curve_refused": 2.0, "commands_rejected": float(refusals["n"]), "wakeups": 1.0}

    with TelemetryPublisher(pub, RATES, stats=stats) as telemetry:
        telemetry.endpoint = pub.endpoint
        telemetry.signer = signer
        yield telemetry
    pub.close()


def test_list_shows_each_topic_at_the_rate_it_was_sent(robot):
    code, out, _ = _topic("list", "--endpoint", robot.endpoint, "--duration", "2.5", "--json")
    assert code == 0
    topics = json.loads(out)["robots"]["cell1"]["topics"]
    check_rates({t: topics[t] for t in RATES}, robot)
    for topic in RATES:
        assert topics[topic]["sessions"] == {f"{robot.session:016x}": topics[topic]["count"]}
    assert topics["video"] == {"count": 0}


def test_hz_reports_every_second_over_its_window(robot):
    code, out, _ = _topic(
        "hz",
        "--endpoint",
        robot.endpoint,
        "--topic",
        "stimulus",
        "--count",
        "3",
        "--window",
        "2",
        "--json",
    )
    assert code == 0
    reports = [json.loads(line) for line in out.splitlines()]
    assert len(reports) == 3
    last = reports[-1]["robots"]["cell1"]["topics"]
    assert set(last) == {"stimulus"}
    stim = last["stimulus"]
    assert stim["in_window"] < stim["count"]  # three seconds read, the rates over the last two
    assert stim["rate_hz"] == pytest.approx(stim["sent_hz"], rel=0.10)
    assert stim["sent_hz"] > RATES["stimulus"] / 2
    # the gaps between two stimuli straddle the period (20 ms at 50 Hz)
    assert last["stimulus"]["gap_min_ms"] <= 20.0 <= last["stimulus"]["gap_max_ms"]


def test_echo_decodes_a_stimulus_and_names_its_signer(robot, tmp_path):
    key = tmp_path / "cell1.sign"
    key.write_text(robot.signer.public.hex() + "\n")
    code, out, _ = _topic(
        *("echo", "--endpoint", robot.endpoint, "--topic", "stimulus", "--count", "2"),
        *("--json", "--robot-key", str(key)),
    )
    assert code == 0
    first, second = (json.loads(line) for line in out.splitlines())
    assert (first["robot"], first["topic"], first["signed"]) == ("cell1", "stimulus", "robot key")
    fields = first["fields"]
    assert fields["stimulus"] == CELLS.tolist()
    assert (fields["pattern"], fields["grip_level"], fields["mode"]) == (4, 12, "mask")
    assert fields["signer"] == robot.signer.public.hex()
    assert fields["session"] == robot.session
    assert second["fields"]["seq"] == fields["seq"] + 1


def test_echo_says_when_a_message_is_not_signed_by_the_robot_key(robot, tmp_path):
    key = tmp_path / "other.sign"
    key.write_text(Signer.generate().public.hex() + "\n")
    code, out, _ = _topic(
        *("echo", "--endpoint", robot.endpoint, "--topic", "frame", "--count", "1"),
        *("--robot-key", str(key)),
    )
    assert code == 0
    head, *body = out.splitlines()
    assert head.startswith("--- cell1 frame") and "NOT the robot's" in head
    # a frame is summarized, not printed whole
    (frame,) = [line for line in body if line.startswith("frame:")]
    assert frame == "frame: float32 2x10x10, min 0.5 max 0.5 mean 0.5"
    assert f"session: {robot.session:016x}" in body


def test_list_shows_the_session_and_the_refusals_the_robot_reports(robot):
    code, out, _ = _topic("--endpoint", robot.endpoint, "--duration", "1.5")
    assert code == 0
    assert f"cell1        session {robot.session:016x} (stimulus, frame, heartbeat)" in out
    (refusals,) = [line for line in out.splitlines() if "refusals:" in line]
    assert "curve_refused 2" in refusals
    assert "commands_rejected" in refusals and "while watching" in refusals
    assert "wakeups" not in refusals


@pytest.fixture
def curve_robot(zmq_ctx, keys):
    """cell1 on a CURVE PUB that allows only the operator's key, as a robot's socket does."""
    security = SecurityConfig(
        mode="curve", secret_key_file=keys.robot_secret, authorized_keys_dir=keys.authorized
    )
    auth = Authenticator(zmq_ctx, security)
    (port,) = free_ports(1)
    pub = Publisher(
        zmq_ctx, loopback(port), bind=True, name=b"cell1", sock_opts=server_options(security)
    )
    with TelemetryPublisher(pub, {"heartbeat": 20.0, "stimulus": 20.0}) as telemetry:
        telemetry.endpoint = pub.endpoint
        telemetry.auth = auth
        yield telemetry
    pub.close()
    auth.stop()


def test_an_operator_config_reads_a_curve_robot(curve_robot, keys, tmp_path):
    config = tmp_path / "operator.toml"
    config.write_text(
        "[operator.link]\n"
        f'telemetry_endpoint = "{curve_robot.endpoint}"\n'
        'robot_name = "cell1"\n'
        "[operator.link.security]\n"
        'mode = "curve"\n'
        f'secret_key_file = "{keys.operator_secret}"\n'
        f'server_public_key_file = "{keys.robot_public}"\n'
    )
    code, out, _ = _topic("--config", str(config), "--duration", "1.5", "--json")
    assert code == 0
    topics = json.loads(out)["robots"]["cell1"]["topics"]
    assert topics["heartbeat"]["count"] > 5 and topics["stimulus"]["count"] > 5


def test_a_key_the_robot_does_not_allow_reads_nothing_and_is_told_why(curve_robot, keys, tmp_path):
    from deploy.keys_cli import generate

    _, stranger = generate(tmp_path / "stranger", "stranger")
    code, _, err = _topic(
        *("--endpoint", curve_robot.endpoint, "--duration", "1.5"),
        *("--curve-key", str(stranger), "--server-key", str(keys.robot_public)),
    )
    assert code == 1
    assert "nothing arrived" in err and "allowlist" in err
    assert curve_robot.auth.refused >= 1  # what the robot's heartbeat reports as curve_refused


def test_a_robot_config_is_refused_with_what_to_give_instead(tmp_path):
    config = tmp_path / "robot.toml"
    config.write_text('[robot.link]\ntelemetry_endpoint = "tcp://*:5555"\n')
    with pytest.raises(Exception, match="operator's or a recorder's config"):
        _topic("--config", str(config))


def test_the_fabric_needs_a_robot_name(tmp_path):
    with pytest.raises(Exception, match="--robot NAME"):
        _topic("--router", "quic/127.0.0.1:7447", "--cert-dir", str(tmp_path))


def test_the_command_line_prints_the_rates(robot):
    """``deepxpalm topic hz`` as a user runs it: a process of its own, its table on stdout."""
    proc = subprocess.run(
        [*cli("topic", "hz", "--endpoint", robot.endpoint, "--count", "2")],
        capture_output=True,
        text=True,
        timeout=60,
        env=ENV,
        cwd=REPO,
    )
    assert proc.returncode == 0, proc.stderr
    rows = [line.split() for line in proc.stdout.splitlines() if line.startswith("cell1 ")]
    rates = {row[1]: (float(row[2]), float(row[3])) for row in rows if row[1] in RATES}
    assert set(rates) == set(RATES), proc.stdout
    for topic, (rate, sent) in rates.items():  # what arrived is what was sent (loopback TCP)
        assert rate == pytest.approx(sent, rel=0.10), (topic, proc.stdout)
        assert sent > RATES[topic] / 2, (topic, proc.stdout)


#: how long the command watches a robot node
WATCH_S = 3.0


def test_a_robot_node_is_read_as_it_sends(robot_in_thread):
    """A real robot node: its heartbeats, stimuli and raw frames at the rates it sent them
    (its sequence numbers over its own clock), its session; nothing signed (no key)."""
    from robot_side.node.config import RobotLinkConfig
    from robot_side.node.telemetry import DIRECT_FRAME_DISPLAY_HZ

    tel, cmd = free_ports(2)
    node = robot_in_thread(tel, cmd)
    starved_ms = node.counters["late_wake_ms"]
    code, out, _ = _topic("--endpoint", loopback(tel), "--duration", str(WATCH_S), "--json")
    assert code == 0
    starved_s = (node.counters["late_wake_ms"] - starved_ms) / 1e3
    (robot,) = json.loads(out)["robots"].values()
    topics = robot["topics"]
    for topic in ("heartbeat", "stimulus", "frame"):
        t = topics[topic]
        arrived = t["count"] / (t["count"] + t["lost"])
        assert t["rate_hz"] == pytest.approx(t["sent_hz"] * arrived, rel=0.10), (topic, t)
        assert t["sessions"] == {f"{node.session:016x}": t["count"]}
        assert t["signers"] == {"unsigned": t["count"]}
    # its own pace: about its 20 heartbeats a second, less the time its loop counted itself
    # starved (it runs in a thread of this test's process, which a busy lane starved 0.9 s of a
    # 3 s watch in CI: no heartbeat went out meanwhile); raw frames never above their rate
    heartbeat_hz = RobotLinkConfig().heartbeat_rate_hz
    least = heartbeat_hz / 2 * max(0.0, 1 - starved_s / WATCH_S)
    assert least < topics["heartbeat"]["sent_hz"] < heartbeat_hz * 1.1, (starved_s, topics)
    assert topics["frame"]["sent_hz"] < DIRECT_FRAME_DISPLAY_HZ * 1.1


def test_import_leaves_torch_alone():
    """The command runs where the robot's extras are not installed (an operator PC)."""
    code = (
        "import sys, deploy.topic_cli, deploy.view_cli, deploy.wire_tap; "
        "print(sorted(m for m in ('torch', 'zenoh', 'foxglove', 'mcap') if m in sys.modules))"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=ENV, cwd=REPO
    )
    assert proc.stdout.strip() == "[]", proc.stderr


def test_a_stop_the_operator_sends_shows_latched_in_the_robots_heartbeats(robot_in_thread, zmq_ctx):
    """What the robot did with a command is read on the wire: its heartbeat says the STOP
    latched (commands travel to the robot, never on its telemetry)."""
    from tests_support import ProtocolOperator

    tel, cmd = free_ports(2)
    robot_in_thread(tel, cmd)
    operator = ProtocolOperator(
        Subscriber(zmq_ctx, loopback(tel), bind=False),
        Publisher(zmq_ctx, loopback(cmd), bind=False),
    )
    operator.sync()
    out, err, stop = io.StringIO(), io.StringIO(), threading.Event()
    args = _args("echo", "--endpoint", loopback(tel), "--topic", "heartbeat", "--json")
    reader = threading.Thread(target=topic_cli.watch, args=(args, stop, out, err), daemon=True)
    reader.start()
    operator.pump(0.5)
    operator.command("arm_stop")
    operator.pump(1.0)
    stop.set()
    reader.join(10)
    latched = [
        json.loads(line)["fields"]["stats"].get("arm_stop_latched")
        for line in out.getvalue().splitlines()
    ]
    assert latched[0] == 0.0 and latched[-1] == 1.0, latched
