"""``deploy.units`` against real processes: spawn, stop, READY=1 with what a child bound."""

from __future__ import annotations

import os
import signal
import sys
import time
from pathlib import Path

import pytest

from deploy.units import process
from deploy.units.catalogue import UNITS, UnitSpec, unit
from deploy.units.policy import UNITS_DIR, policy
from deploy.units.readiness import NotifySocket, NotReady
from deploy.units.service import Service

#: a child that ignores SIGTERM, as a wedged node would, and says READY=1
STUBBORN = (
    "import signal, time\n"
    "from common.process.sd_notify import Notifier\n"
    "signal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
    "Notifier().ready('stubborn', {'where': 'nowhere'})\n"
    "time.sleep(60)\n"
)


def _python(code: str) -> list[str]:
    return ["-c", code]


@pytest.fixture
def plain(monkeypatch):
    """``python -c CODE`` for a child instead of ``deepxpalm``: the same spawn otherwise."""
    monkeypatch.setattr(process, "cli_argv", lambda argv, _module: [sys.executable, *argv])


def test_stop_ends_a_child_by_sigterm_and_kills_one_that_ignores_it(tmp_path, plain):
    polite = process.spawn(None, _python("import time; time.sleep(60)"), tmp_path / "p.log")
    notify = NotifySocket("stubborn")
    env = {**os.environ, **notify.environ()}
    stubborn = process.spawn(None, _python(STUBBORN), tmp_path / "s.log", env)
    notify.started(stubborn.pid)
    try:
        assert notify.wait_ready(stubborn, 60).endpoints == {"where": "nowhere"}
        assert process.stop(polite, 5) is False  # ended by SIGTERM, not killed
        assert polite.returncode == -signal.SIGTERM
        t0 = time.monotonic()
        assert process.stop(stubborn, 0.3) is True
        assert stubborn.returncode == -signal.SIGKILL
        assert time.monotonic() - t0 < 5  # waited its 0.3 s, then killed: no hang
        assert process.stop(stubborn) is False  # already ended: left alone
    finally:
        process.stop(polite, 0)
        process.stop(stubborn, 0)
        notify.close()


def test_a_stopped_child_is_continued_so_it_ends_by_its_signal(tmp_path, plain):
    child = process.spawn(None, _python("import time; time.sleep(60)"), tmp_path / "c.log")
    child.send_signal(signal.SIGSTOP)
    assert process.stop(child, 5) is False and child.returncode == -signal.SIGTERM


def test_the_cli_is_run_by_this_interpreter_and_writes_its_log(tmp_path):
    assert process.cli_argv(["-v", "demo"]) == [sys.executable, "-m", "deploy.cli", "-v", "demo"]
    log = tmp_path / "help.log"
    child = process.spawn("robot", ["--help"], log)  # at the robot unit's niceness, if allowed
    assert child.wait(60) == 0 and "deepxpalm" in log.read_text()


def test_a_child_that_ends_before_ready_raises_with_its_log(tmp_path, plain):
    code = "import sys; print('no device on /dev/ttyUSB0', file=sys.stderr); sys.exit(3)"
    service = Service(UnitSpec("board", (), "a test", "nothing"), _python(code), tmp_path / "b.log")
    try:
        with pytest.raises(NotReady, match=r"board .* ended with 3 .*no device on /dev/ttyUSB0"):
            service.up(30)
    finally:
        service.close()


def test_a_silent_child_is_not_ready_after_its_timeout_and_is_stopped(tmp_path, plain):
    spec = UnitSpec("mute", (), "a test", "nothing")
    service = Service(spec, _python("import time; time.sleep(60)"), tmp_path / "m.log")
    try:
        with pytest.raises(NotReady, match=r"not ready after 0\.5 s"):
            service.up(0.5)
        assert not service.alive()  # stopped, as systemd's TimeoutStartSec= does
    finally:
        service.close()


GRANDPARENT = """
import os, subprocess, sys, time
from common.process.sd_notify import Notifier
subprocess.run([sys.executable, "-c",
    "from common.process.sd_notify import Notifier; Notifier().ready('not mine', {'x': 1})"])
time.sleep(0.5)
Notifier().ready('mine', {'x': 2})
time.sleep(60)
"""


def test_only_the_process_started_speaks_for_the_unit(tmp_path, plain):
    """NotifyAccess=main: a grandchild that inherited $NOTIFY_SOCKET is not the unit."""
    service = Service(UnitSpec("parent", (), "a test", "x"), _python(GRANDPARENT), tmp_path / "g")
    try:
        assert service.up(30).endpoints == {"x": 2}
    finally:
        service.stop(0)
        service.close()


def test_a_simulator_binds_port_0_and_says_its_port(tmp_path):
    config = tmp_path / "gripper.toml"
    config.write_text("port = 0\n")
    service = Service("sim-gripper", ["sim", "gripper", "--config", str(config)], tmp_path / "g")
    try:
        ready = service.up()
        port = ready.endpoints["port"]
        assert isinstance(port, int) and port > 0 and ready.status == "gripper simulator"
        assert f'"port": {port}' in service.log_text()  # the line for people, beside it
        service.stop()
        service.start()  # a restart keeps its socket: its new process is listened to
        assert service.wait_ready().endpoints["port"] > 0
        assert len(service.notify.readies()) == 2
    finally:
        service.stop()
        service.close()


def test_every_shipped_unit_is_in_the_catalogue_with_its_rules():
    shipped = {p.stem.removeprefix("deepxpalm-") for p in UNITS_DIR.glob("*.service")}
    assert shipped <= {spec.unit for spec in UNITS.values()}
    assert unit("robot").policy.restart_sec == 3.0  # deploy/systemd/deepxpalm-robot.service
    assert unit("operator").stop_post[:2] == ("palm", "lift")  # its ExecStopPost=
    assert unit("operator").policy.watchdog_sec > 0
    assert unit("sim-ur").policy.restart == "on-failure"  # a device comes back by itself
    for spec in UNITS.values():
        assert spec.ready and spec.command, spec.name
        assert Path(process.cli_argv(spec.argv())[2]) == Path("deploy.cli")


def test_a_name_not_in_the_catalogue_says_which_are():
    with pytest.raises(KeyError, match="robot"):
        unit("robott")


def test_a_unit_above_other_work_weighs_its_group_as_its_niceness_weighs_a_thread():
    """Nice= ranks threads only inside the unit's own group (systemd gives each service a
    control group and a session of its own); CPUWeight= is what ranks the unit against other
    work. The kernel weighs a thread about 1.25 times more per step of niceness."""
    ranked = [p for p in map(policy, ("robot", "operator", "router")) if p is not None]
    assert len(ranked) == 3
    for unit_policy in ranked:
        assert unit_policy.nice is not None and unit_policy.nice < 0, unit_policy
        assert unit_policy.cpu_weight is not None, f"{unit_policy.unit}: Nice= without CPUWeight="
        thread_ratio = 1.25**-unit_policy.nice
        assert 0.8 <= (unit_policy.cpu_weight / 100) / thread_ratio <= 1.25, unit_policy
