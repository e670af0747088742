"""Shared fixtures: every socket on loopback, every port random, nothing hangs."""

from __future__ import annotations

import ast
import contextlib
import json
import os
import tempfile
from pathlib import Path

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


@pytest.hookimpl(trylast=True)  # after pytest's own tmp_path plugin has set up its folder
def pytest_configure(config: pytest.Config) -> None:
    """What the product and the processes it starts put in the temp folder (a demo's logs, a
    fleet's keys and logs, a simulated device's link) goes under pytest's own folder, which
    keeps the last three runs: a suite run left 28 MB in /tmp, and a machine that runs CI
    again and again fills up. Set before collection: modules copy the environment when
    imported, for the processes they start."""
    folder = config._tmp_path_factory.mktemp("tmp", numbered=False)
    os.environ["TMPDIR"] = str(folder)
    tempfile.tempdir = None  # read again from TMPDIR


#: each test file's measured time (scripts/file-durations.py writes it from a lane's report)
FILE_DURATIONS = Path(__file__).with_name("file_durations.json")

#: Files whose tests share no module fixture and each start a whole deployment of their own,
#: and whose file is among the longest of its lane: a lane hands their tests out one by one
#: rather than the file whole. Whole, the fault matrix's cells (80 s) and the two stop-latch
#: pages (75 s) ran one after the other on one worker while the other workers ran out of work;
#: in the serial lane, the video pages through the link simulator (40 s) and the demo's
#: (24 s). A module fixture added to one of these would start once per worker that runs it.
EACH_TEST_ON_ITS_OWN = frozenset(
    {
        "tests/faults/test_fault_matrix.py",
        "tests/dashboard/test_stop_latch_browser.py",
        "tests/dashboard/test_video_netsim_browser.py",
        "tests/dashboard/test_demo_video_browser.py",
    }
)


def unit_of(nodeid: str) -> str:
    """What a lane hands a worker a test with: its file, or the test alone
    (``EACH_TEST_ON_ITS_OWN``); ``file_durations.json`` times the units by these names."""
    file = nodeid.split("::", 1)[0]
    return nodeid if file in EACH_TEST_ON_ITS_OWN else file


def pytest_xdist_make_scheduler(config: pytest.Config, log: object) -> object | None:
    """``--dist loadfile``, but in the units of :func:`unit_of`."""
    if config.getoption("dist", None) != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class ByUnit(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return unit_of(nodeid)

    return ByUnit(config, log)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The soak runs only when a -m expression names it; the longest files come first.

    pyproject's addopts say ``-m 'not soak'``, but a -m on the command line (the fast
    lane's ``-m "not slow"``) replaces that one, and would start the 30-minute soak.

    The lanes hand whole files to their workers in this order (``--no-loadscope-reorder``
    in the Makefile; pytest-xdist's own order puts the files with the most tests first,
    and a long file of one test could start last while the other workers ran out of
    work). Longest first, the shortest at the end: a lane ends near its average. A test
    file keeps its tests' order, and a file the measurements do not name keeps its place
    after the named ones; the tests of ``EACH_TEST_ON_ITS_OWN`` are placed one by one.
    """
    if "soak" not in (config.getoption("markexpr") or ""):
        soak = [item for item in items if item.get_closest_marker("soak")]
        if soak:
            config.hook.pytest_deselected(items=soak)
            items[:] = [item for item in items if not item.get_closest_marker("soak")]
    seconds = json.loads(FILE_DURATIONS.read_text()) if FILE_DURATIONS.exists() else {}

    def took(item: pytest.Item) -> float:
        """The unit's time; a test handed out alone and not measured alone, its file's."""
        file = item.nodeid.split("::", 1)[0]
        return seconds.get(unit_of(item.nodeid), seconds.get(file, 0.0))

    items.sort(key=lambda item: -took(item))


def pytest_addoption(parser: pytest.Parser) -> None:
    group = parser.getgroup("deepxpalm lanes")
    group.addoption(
        "--write-test-index",
        metavar="PATH",
        help="after a complete collection, write each test file's tests' markers to PATH",
    )
    group.addoption(
        "--test-index",
        metavar="PATH",
        help="import only the test files whose tests (by PATH, --write-test-index's) -m selects;"
        " give it as --test-index=PATH (pytest would take a lone PATH for a test path)",
    )


#: each collected test's file and marker names, for --write-test-index
_COLLECTED = pytest.StashKey[list[tuple[str, list[str]]]]()


def pytest_itemcollected(item: pytest.Item) -> None:
    if item.config.getoption("write_test_index", None):
        names = sorted({mark.name for mark in item.iter_markers()})
        item.config.stash.setdefault(_COLLECTED, []).append((item.nodeid.split("::", 1)[0], names))


def pytest_collection_finish(session: pytest.Session) -> None:
    """The test index: for each test file, the sets of marker names its tests carry (the soak's
    too: recorded as collected, before any -m). Written only when nothing failed to collect; an
    index not written leaves the lanes collecting every file."""
    path = session.config.getoption("write_test_index", None)
    if not path or session.testsfailed:
        return
    index: dict[str, list[list[str]]] = {}
    for file, names in session.config.stash.get(_COLLECTED, []):
        if names not in index.setdefault(file, []):
            index[file].append(names)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(index, indent=0, sort_keys=True))


def _files_to_skip(config: pytest.Config) -> frozenset[str]:
    """The files the test index names none of whose tests the -m expression selects.

    Every worker of a lane collected every test file, importing what each imports (the
    nodes, aiortc, mujoco, numba's entry points), for the few files its lane runs: the
    alone lane runs 4 files of about 180, the serial lane about 20. With
    ``--test-index`` (the Makefile's lanes; the index is the setup's collection of the same
    tree) a file with no selected test is not imported. A file the index does not name is
    collected as before; without an index, or with a -m this cannot read, every file is.
    """
    path = config.getoption("test_index", None)
    expr_text = config.getoption("markexpr", None) or ""
    if not path or not Path(path).exists() or not expr_text:
        return frozenset()
    try:
        expr = ast.parse(expr_text, mode="eval").body
        index = json.loads(Path(path).read_text())
        return frozenset(
            file for file, sets in index.items() if not any(_selects(expr, n) for n in sets)
        )
    except Exception:  # an index or an expression this cannot read: collect every file
        return frozenset()


def _selects(node: ast.AST, names: list[str]) -> bool:
    """Whether a -m expression of marker names, ``and``, ``or``, ``not`` and parentheses (the
    lanes' kind) selects a test with these markers; anything else in it (a marker's
    arguments) raises, and the lanes collect every file."""
    if isinstance(node, ast.BoolOp):
        parts = (_selects(value, names) for value in node.values)
        return all(parts) if isinstance(node.op, ast.And) else any(parts)
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.Not):
        return not _selects(node.operand, names)
    if isinstance(node, ast.Name):
        return node.id in names
    raise ValueError(f"not a plain marker expression: {ast.dump(node)}")


_SKIPPED_FILES = pytest.StashKey[frozenset[str]]()


def pytest_ignore_collect(collection_path: Path, config: pytest.Config) -> bool | None:
    if not collection_path.name.startswith("test_") or collection_path.suffix != ".py":
        return None
    if _SKIPPED_FILES not in config.stash:
        config.stash[_SKIPPED_FILES] = _files_to_skip(config)
    skipped = config.stash[_SKIPPED_FILES]
    if not skipped:
        return None
    try:
        relative = collection_path.relative_to(config.rootpath).as_posix()
    except ValueError:
        return None
    return True if relative in skipped else None


@pytest.fixture
def zmq_ctx():
    import zmq

    ctx = zmq.Context()
    yield ctx
    ctx.destroy(linger=0)


@pytest.fixture
def arm_sims():
    """Two simulated UR controllers on their real wire (the fleet tests' two cells)."""
    from robot_side.arm.sim import URSimProcess

    sims = [URSimProcess().start(), URSimProcess().start()]
    yield sims
    for sim in sims:
        sim.stop()


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


@pytest.fixture(scope="module")
def robot_node_priority_module():
    """Every thread of this process at the robot unit's niceness (``Nice=-10``, the operator's
    too) for a module whose fixture drives a UR arm from the test process, as the robot node
    does from its own, or runs the nodes as threads of it.

    The driver's keep-alive thread runs at that niceness already, but each kick needs the
    GIL, and the lanes run the test process at -5, below three deployments' nodes and
    simulators at -10: a test thread holding the GIL got so little CPU that the kicks
    stopped for 162 ms and the arm's controller stopped the program (its window is 150 ms).
    That is this process standing below the node it stands for, not the node. Where the
    process may not raise a priority, nothing changes. Each thread gets its own back after.
    """
    from deploy.units.policy import unit_nice
    from harness.processes import raise_threads

    nice = unit_nice("robot")
    before = raise_threads(os.getpid(), nice) if nice is not None else {}
    yield
    for tid, own in before.items():
        with contextlib.suppress(OSError):  # a thread that ended meanwhile
            os.setpriority(os.PRIO_PROCESS, tid, own)


@pytest.fixture(scope="session")
def lerobot(tmp_path_factory):
    """One LeRobot interpreter for every load a test process asks: importing LeRobot costs
    about 12 s of CPU, a load of a demo's dataset a second or two. Started at the first test
    that asks for it; a worker that runs no such test starts none."""
    from lerobot_env import LeRobot

    with LeRobot(tmp_path_factory.mktemp("lerobot"), policies=True) as server:
        yield server
