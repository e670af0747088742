"""The CPU each test costs, its processes included, and where a lane's time goes.

A pytest plugin and its report. Each pytest process (every xdist worker, or
the lane's one process) moves itself into a cgroup of its own, which every
process a test starts inherits (nodes, simulators, browsers, whatever they
start in turn); a test's CPU is the cgroup's usage across its setup, call and
teardown. Needs a writable cgroup: the v1 ``cpuacct`` hierarchy, or v2 with
the ``cpu`` controller (usually root).

    PYTHONPATH=scripts CPU_PER_TEST=/tmp/cpu.jsonl make test ARGS="-p cpu_per_test"
    python scripts/cpu_per_test.py /tmp/cpu.jsonl

The report gives each lane's CPU against its length (a lane of two cores
whose tests use a third of them waits, it does not compute) and its files
by the time they hold the lane's workers (their wall time over the lane's
worker count): what shortens the lane most.
"""

from __future__ import annotations

import json
import os
import sys
import time
from collections import defaultdict
from pathlib import Path

import pytest

V1 = Path("/sys/fs/cgroup/cpuacct")
V2 = Path("/sys/fs/cgroup")
_group: Path | None = None


def _usage_s() -> float:
    assert _group is not None
    if (_group / "cpuacct.usage").exists():
        return int((_group / "cpuacct.usage").read_text()) / 1e9
    stat = dict(line.split() for line in (_group / "cpu.stat").read_text().splitlines())
    return int(stat["usage_usec"]) / 1e6


def pytest_configure(config) -> None:
    global _group
    worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
    root = V1 if V1.is_dir() else V2
    _group = root / f"deepxpalm-test-{os.getpid()}-{worker}"
    try:
        _group.mkdir(exist_ok=True)
        (_group / "cgroup.procs").write_text(str(os.getpid()))
    except OSError as e:
        raise SystemExit(f"cpu_per_test: cannot make a cgroup at {_group}: {e} (root?)") from e


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    start_cpu, start = _usage_s(), time.monotonic()
    outcome = yield
    config = item.config
    row = {
        "id": item.nodeid,
        "cpu_s": round(_usage_s() - start_cpu, 2),
        "wall_s": round(time.monotonic() - start, 2),
        "lane": config.getoption("markexpr", ""),
        "workers": int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")),
    }
    with open(os.environ.get("CPU_PER_TEST", "cpu-per-test.jsonl"), "a") as f:
        f.write(json.dumps(row) + "\n")
    return outcome


def report(path: str, top: int = 12) -> None:
    cores = os.cpu_count() or 1
    with open(path) as f:
        rows = [json.loads(line) for line in f]
    lanes: dict[str, list[dict]] = defaultdict(list)
    for r in rows:
        lanes[r["lane"]].append(r)
    for lane, lane_rows in lanes.items():
        workers = lane_rows[0]["workers"]
        cpu = sum(r["cpu_s"] for r in lane_rows)
        held = sum(r["wall_s"] for r in lane_rows) / workers
        print(f"{lane or '(no -m)'}\n  {workers} workers, {len(lane_rows)} tests: {cpu:.0f} CPU-s,")
        print(
            f"  {held:.0f} s of the lane's workers' time: {cpu / held / cores:.0%} of {cores} cores"
        )
        files: dict[str, list[float]] = defaultdict(lambda: [0.0, 0.0])
        for r in lane_rows:
            f = files[r["id"].split("::")[0]]
            f[0] += r["wall_s"] / workers
            f[1] += r["cpu_s"]
        for name, (lane_s, cpu_s) in sorted(files.items(), key=lambda kv: -kv[1][0])[:top]:
            print(f"  {lane_s:6.1f} s of the lane  {cpu_s:6.1f} CPU-s  {name}")


if __name__ == "__main__":
    if len(sys.argv) != 2:
        print("usage: python scripts/cpu_per_test.py CPU_PER_TEST.jsonl", file=sys.stderr)
        sys.exit(2)
    report(sys.argv[1])
