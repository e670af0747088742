"""The harness's process toolkit against real child processes."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

from harness import processes

#: a child that ignores SIGTERM, as a wedged node would, and says when it is ready
STUBBORN = (
    "import signal, sys, time\n"
    "signal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
    "print('up', flush=True)\n"
    "time.sleep(60)\n"
)


def test_stop_ends_a_child_by_sigterm_and_kills_one_that_ignores_it():
    polite = subprocess.Popen(["sleep", "60"])
    stubborn = subprocess.Popen([sys.executable, "-c", STUBBORN], stdout=subprocess.PIPE)
    try:
        assert stubborn.stdout.readline() == b"up\n"
        assert processes.cmdline(polite.pid) == ["sleep", "60"]
        assert {polite.pid, stubborn.pid} <= set(processes.children_of(os.getpid()))
        assert processes.stop(polite, 5) is False  # ended by SIGTERM, not killed
        assert polite.returncode == -signal.SIGTERM
        t0 = time.monotonic()
        assert processes.stop(stubborn, 0.3) is True
        assert stubborn.returncode == -signal.SIGKILL
        assert time.monotonic() - t0 < 5  # waited its 0.3 s, then killed: no hang
        assert processes.stop(stubborn) is False  # already ended: left alone
        assert processes.cmdline(polite.pid) is None  # reaped: gone from /proc
    finally:
        for p in (polite, stubborn):
            if p.poll() is None:
                p.kill()
                p.wait()


def test_the_cli_is_run_by_this_interpreter_with_its_arguments():
    assert processes.cli_argv(["-v", "demo"]) == [sys.executable, "-m", "deploy.cli", "-v", "demo"]
    proc = processes.spawn_cli(["--help"], subprocess.PIPE, unit="robot")  # at its niceness
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0 and b"deepxpalm" in out


def test_cpu_readers_of_this_process():
    busy_until = time.process_time() + 0.05
    while time.process_time() < busy_until:
        pass
    assert processes.process_cpu_s(os.getpid()) >= 0.05
    assert processes.thread_cpu_s(os.getpid())["main"] > 0
    idle, total = processes.machine_cpu()
    assert 0 < idle < total
    assert 0.0 <= processes.idle_share((0.0, 0.0), (idle, total)) <= 1.0
