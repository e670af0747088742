"""Shared fixtures: every socket on loopback, every port random, nothing hangs."""

from __future__ import annotations

import os

import pytest
from hypothesis import HealthCheck, settings

# CI is derandomized: the same examples every run, so a red CI is a regression, not a
# lucky draw (and a green one is not luck either). "random" draws new examples each run
# to find new cases: HYPOTHESIS_PROFILE=random make test. "dev" is the default elsewhere.
settings.register_profile(
    "ci",
    max_examples=200,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.register_profile("dev", max_examples=100, deadline=None)
settings.register_profile(
    "random", max_examples=1000, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
settings.load_profile(
    os.environ.get("HYPOTHESIS_PROFILE") or ("ci" if os.environ.get("CI") else "dev")
)


#: Modules that keep a test worker busy for a quarter of a minute or more, longest first
#: (measured with ``--junitxml`` on a quiet 2-core machine). A lane hands its files to its
#: workers in this order (``--dist loadfile --no-loadscope-reorder`` in the Makefile), then
#: the rest in collection order: a long file handed out last keeps the lane waiting on one
#: worker while the others idle. Order only; add a module when its file takes that long.
LONG_MODULES = (
    "tests/bench/test_bench_quick.py",  # 61 s
    "tests/lab/test_lab_world.py",  # 60 s
    "tests/faults/test_fault_matrix.py",  # about 55 s
    "tests/dashboard/test_video_netsim_browser.py",  # about 50 s
    "tests/export/test_curation.py",  # 38 s
    "tests/system/test_command_path.py",  # 37 s
    "tests/lab/test_task.py",  # 37 s
    "tests/recording/test_foxglove.py",  # 36 s
    "tests/export/test_export_roundtrip.py",  # 35 s
    "tests/relay/test_fleet.py",  # 33 s
    "tests/video/test_video_privilege.py",  # 29 s
    "tests/system/test_stop_replay.py",  # 27 s
    "tests/dashboard/test_arm_jog_browser.py",  # 25 s
    "tests/robot/test_assist.py",  # 21 s
    "tests/fuzz/test_fuzz_operator.py",  # 21 s
    "tests/system/test_node_death.py",  # 20 s
    "tests/relay/test_telemetry_replay.py",  # 19 s
    "tests/study/test_study_session.py",  # 18 s
    "tests/system/test_devices_cli.py",  # 17 s
    "tests/system/test_processes.py",  # 17 s
    "tests/drivers/test_ur.py",  # 17 s
    "tests/drivers/test_ur_watchdog.py",  # 16 s
    "tests/fuzz/test_fuzz_robot.py",  # 16 s
    "tests/relay/test_video_over_relay.py",  # 15 s
)


def _long_first(item: pytest.Item) -> int:
    path = item.nodeid.split("::", 1)[0]
    return LONG_MODULES.index(path) if path in LONG_MODULES else len(LONG_MODULES)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The long modules first (``LONG_MODULES``); the soak only when a -m expression names it.

    pyproject's addopts say ``-m 'not soak'``, but a -m on the command line (the fast
    lane's ``-m "not slow"``) replaces that one, and would start the 30-minute soak.
    """
    items.sort(key=_long_first)  # stable: each module keeps its own order
    if "soak" in (config.getoption("markexpr") or ""):
        return
    soak = [item for item in items if item.get_closest_marker("soak")]
    if soak:
        config.hook.pytest_deselected(items=soak)
        items[:] = [item for item in items if not item.get_closest_marker("soak")]


@pytest.fixture
def zmq_ctx():
    import zmq

    ctx = zmq.Context()
    yield ctx
    ctx.destroy(linger=0)


@pytest.fixture
def quiet_gc():
    """The test process's heap frozen for one timing-sensitive test.

    After a few hundred tests (torch among the imports) a full collection in
    this process takes a hundred milliseconds or more and stops every thread:
    an in-process simulator misses its reply window, a test-side operator
    falls silent long enough for the robot's deadman. The nodes freeze their
    own startup heap for the same reason (``freeze_startup_heap``).
    """
    import gc

    outer = gc.get_freeze_count() > 0  # a module's freeze (quiet_gc_module) outlives this test
    gc.collect()
    gc.freeze()
    yield
    if not outer:
        gc.unfreeze()


@pytest.fixture(scope="module")
def quiet_gc_module():
    """The heap frozen for a whole module, for one whose fixture keeps a UR arm connected.

    A full collection holds the GIL for its whole length (hundreds of
    milliseconds here), and the arm's controller stops the program when the
    driver's kicks stop for its watchdog window (docs/arm.md). Request it
    before the arm connects; ``quiet_gc`` inside keeps this freeze.
    """
    import gc

    gc.collect()
    gc.freeze()
    yield
    gc.unfreeze()


@pytest.fixture(scope="session")
def lerobot(tmp_path_factory):
    """One LeRobot interpreter for every load a test process asks: importing LeRobot costs
    about 12 s of CPU, a load of a demo's dataset a second or two. Started at the first test
    that asks for it; a worker that runs no such test starts none."""
    from lerobot_env import LeRobot

    with LeRobot(tmp_path_factory.mktemp("lerobot"), policies=True) as server:
        yield server
