"""A SIGTERM stops a process wherever its main thread is, including inside its stop event's wait.

CPython runs a signal handler between two bytecodes of the main thread,
also while that thread holds the stop event's internal lock (both ends of
every ``Event.wait``). A handler that calls ``Event.set()`` there deadlocks
the process: it keeps running and ignores SIGTERM. The fault matrix met it
by chance (netsim relayed on for 20 s after a clean restart's SIGTERM); the
child below puts the signal in that window every time, by holding the lock
while it signals itself, and the test reads from outside whether the
process ended.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from tests_support import unanswered_ports

ROOT = Path(__file__).resolve().parents[2]

# the main thread inside Event.wait's locked stretch when SIGTERM arrives
_CHILD = textwrap.dedent(
    """
    import os, signal, sys
    from {module} import stop_on_signals

    stop = stop_on_signals()
    with stop._cond:  # what Event.wait holds at its start and its end
        os.kill(os.getpid(), signal.SIGTERM)
        for _ in range(1000):  # bytecodes: the handler runs in here
            pass
    print("stopping" if stop.wait(10) else "never told to stop", flush=True)
    """
)


@pytest.mark.parametrize("module", ["common.process.signals", "common.process.command_line"])
def test_sigterm_inside_the_stop_events_own_lock_still_stops_the_process(module: str) -> None:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    child = subprocess.Popen(
        [sys.executable, "-c", _CHILD.format(module=module)],
        stdout=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        out, _ = child.communicate(timeout=15)
    except subprocess.TimeoutExpired:
        child.kill()
        child.communicate()
        pytest.fail(
            "the process hung on SIGTERM: its signal handler blocked on the lock the main "
            "thread held (product: a handler must not take locks)"
        )
    assert out.strip() == "stopping", out


def test_the_link_simulator_ends_on_sigterm_while_it_relays(tmp_path: Path) -> None:
    """``deepxpalm netsim`` in stream mode as its unit runs it, up (its READY=1), SIGTERM: it
    ends. The robot's ends are ports this test holds listening; the operator's, its own."""
    from deploy.units.service import Service

    with unanswered_ports(2) as (tel, cmd):
        args = ["-v", "netsim", "--mode", "stream"]
        args += ["--robot-telemetry", f"tcp://127.0.0.1:{tel}"]
        args += ["--robot-commands", f"tcp://127.0.0.1:{cmd}"]
        args += ["--operator-telemetry", "tcp://127.0.0.1:0"]
        args += ["--operator-commands", "tcp://127.0.0.1:0"]
        netsim = Service("netsim", args, tmp_path / "netsim.log", watchdog=False)
        try:
            assert "operator_telemetry" in netsim.up(30).endpoints
            t0 = time.monotonic()
            killed = netsim.stop(10, signal.SIGTERM)
            assert not killed and netsim.popen.returncode == 0, netsim.log_tail()
            assert time.monotonic() - t0 < 10
        finally:
            netsim.stop(0)
            netsim.close()
