"""The harness's /proc readers against real child processes."""

from __future__ import annotations

import os
import subprocess
import time

from harness import processes


def test_the_command_line_and_children_of_a_process_until_it_is_reaped():
    child = subprocess.Popen(["sleep", "60"])
    try:
        deadline = time.monotonic() + 5.0  # between fork and exec its command line is empty
        while processes.cmdline(child.pid) == [""] and time.monotonic() < deadline:
            time.sleep(0.01)
        assert processes.cmdline(child.pid) == ["sleep", "60"]
        assert child.pid in processes.children_of(os.getpid())
        assert processes.cpu_s(child.pid) is not None and processes.rss_mb(child.pid) is not None
    finally:
        child.kill()
        child.wait()
    assert processes.cmdline(child.pid) is None  # reaped: gone from /proc
    assert processes.cpu_s(child.pid) is None


def test_cpu_readers_of_this_process():
    busy_until = time.process_time() + 0.05
    while time.process_time() < busy_until:
        pass
    assert processes.process_cpu_s(os.getpid()) >= 0.05
    assert processes.thread_cpu_s(os.getpid())["main"] > 0
    idle, total = processes.machine_cpu()
    assert 0 < idle < total
    assert 0.0 <= processes.idle_share((0.0, 0.0), (idle, total)) <= 1.0
