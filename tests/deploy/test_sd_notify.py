"""sd_notify speaks systemd's datagram protocol, and the watchdog follows the node's loop."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import threading
import time
import uuid
from pathlib import Path

import pytest
from deploy_support import ENV, EXAMPLES, cli
from tests_support import ROBOT_BINDS_ITS_PORTS, unanswered_ports

from common.process.sd_notify import Notifier, watch_node


class FakeSystemd:
    """The receiving end of $NOTIFY_SOCKET: an AF_UNIX datagram socket."""

    def __init__(self, address: str) -> None:
        self.env_value = address
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind("\0" + address[1:] if address.startswith("@") else address)
        self.sock.settimeout(0.1)

    def messages(self, until: float) -> list[str]:
        out = []
        deadline = time.monotonic() + until
        while time.monotonic() < deadline:
            try:
                out.append(self.sock.recv(4096).decode())
            except TimeoutError:
                continue
        return out

    def wait_for(self, text: str, timeout_s: float) -> list[str]:
        seen: list[str] = []
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                seen.append(self.sock.recv(4096).decode())
            except TimeoutError:
                continue
            if any(text in m for m in seen):
                return seen
        raise AssertionError(f"no {text!r} within {timeout_s} s; got {seen}")

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def systemd(tmp_path):
    fake = FakeSystemd(str(tmp_path / "notify.sock"))
    yield fake
    fake.close()


def test_outside_systemd_nothing_is_sent():
    notifier = Notifier({})
    assert not notifier.enabled
    assert not notifier.ready()
    assert notifier.watchdog_interval_s is None


def test_ready_status_and_watchdog_arrive_as_datagrams(systemd):
    notifier = Notifier({"NOTIFY_SOCKET": systemd.env_value, "WATCHDOG_USEC": "2000000"})
    assert notifier.watchdog_interval_s == 2.0
    assert notifier.ready("up")
    assert notifier.watchdog()
    assert notifier.stopping()
    assert systemd.messages(0.3) == ["READY=1\nSTATUS=up", "WATCHDOG=1", "STOPPING=1"]


def test_abstract_socket_names_start_with_at():
    fake = FakeSystemd(f"@deepxpalm-test-{uuid.uuid4().hex}")
    try:
        assert Notifier({"NOTIFY_SOCKET": fake.env_value}).ready()
        assert fake.messages(0.2) == ["READY=1"]
    finally:
        fake.close()


def test_watchdog_meant_for_another_process_is_not_ours(systemd):
    env = {"NOTIFY_SOCKET": systemd.env_value, "WATCHDOG_USEC": "1000000"}
    assert Notifier({**env, "WATCHDOG_PID": str(os.getpid() + 1)}).watchdog_interval_s is None
    assert Notifier({**env, "WATCHDOG_PID": str(os.getpid())}).watchdog_interval_s == 1.0


def test_a_vanished_socket_never_raises(tmp_path):
    notifier = Notifier({"NOTIFY_SOCKET": str(tmp_path / "gone.sock")})
    assert notifier.enabled
    assert not notifier.ready()
    assert not notifier.watchdog()


class _Pub:
    sent = 0


class FakeNode:
    def __init__(self) -> None:
        self.pub = None
        self.link_state = "down"


@pytest.mark.slow
def test_watch_pings_only_while_the_node_publishes(systemd):
    node, stop = FakeNode(), threading.Event()
    notifier = Notifier({"NOTIFY_SOCKET": systemd.env_value, "WATCHDOG_USEC": "400000"})
    watch = watch_node(node, stop, notifier)
    try:
        assert systemd.messages(0.3) == [], "nothing before the sockets are up"
        node.pub = _Pub()
        assert systemd.messages(0.3) == [], "nothing before the loop sends"
        node.pub.sent = 1
        systemd.wait_for("READY=1", 1.0)
        for _ in range(8):  # the loop runs: each poll that sees progress earns a ping
            node.pub.sent += 5
            time.sleep(0.1)
        pinged = [m for m in systemd.messages(0.2) if m == "WATCHDOG=1"]
        assert len(pinged) >= 3
        # The loop wedges: no more pings, so systemd's watchdog would fire.
        assert "WATCHDOG=1" not in systemd.messages(0.6)
    finally:
        stop.set()
        watch.stop()
    assert "STOPPING=1" in systemd.messages(0.3)


def test_watch_follows_a_real_operator_node(systemd, operator_in_thread):
    with unanswered_ports(2) as (tel, cmd):  # nobody at the robot's end
        node = operator_in_thread(tel, cmd)
        stop = threading.Event()
        notifier = Notifier({"NOTIFY_SOCKET": systemd.env_value, "WATCHDOG_USEC": "1000000"})
        watch = watch_node(node, stop, notifier)
        try:
            seen = systemd.wait_for("WATCHDOG=1", 5.0)
            assert any(m.startswith("READY=1") for m in seen)
        finally:
            stop.set()
            watch.stop()


@pytest.mark.slow
def test_robot_process_tells_systemd_it_is_ready_and_alive(systemd, tmp_path):
    """The unit's Type=notify + WatchdogSec, seen from the process: READY=1, then pings.

    ``kill -USR1`` then writes every thread's stack to the journal and the node runs on.
    """
    stderr = tmp_path / "robot.stderr"  # read while it runs: the dump is there at once
    with stderr.open("wb") as err_file:
        proc = subprocess.Popen(
            cli(
                "robot",
                "--config",
                str(EXAMPLES / "robot.toml"),
                "--set",
                'tactile={kind="scripted"}',
                "--set",
                'gripper={kind="none"}',
                "--set",
                'arm={kind="none"}',
                "--set",
                'link.security={mode="plain"}',
                *ROBOT_BINDS_ITS_PORTS,
            ),
            env={**ENV, "NOTIFY_SOCKET": systemd.env_value, "WATCHDOG_USEC": "2000000"},
            stdout=subprocess.DEVNULL,
            stderr=err_file,
        )
    try:
        seen = systemd.wait_for("WATCHDOG=1", 20.0)
        (ready,) = [m for m in seen if m.startswith("READY=1")]
        assert "tcp://127.0.0.1:" in ready and "tcp://127.0.0.1:0" not in ready, ready
        proc.send_signal(signal.SIGUSR1)
        try:
            systemd.wait_for("WATCHDOG=1", 5.0)  # still alive and publishing after the dump
        except AssertionError as e:  # the dump says where each thread was, the log why
            e.add_note(f"the node's stderr:\n{stderr.read_text()[-4000:]}")
            raise
        assert proc.poll() is None
    finally:
        proc.terminate()
        proc.wait(timeout=15)
    dump = stderr.read_text()
    assert proc.returncode == 0, dump
    assert "most recent call first" in dump and "in run" in dump, dump[-2000:]
    assert Path(systemd.env_value).exists()
