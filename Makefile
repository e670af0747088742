# Two commands set up and run everything on a fresh machine (Python 3.11):
#   make demo    - both nodes, simulated devices, the link simulator, a live view
#   make test    - the whole test suite (what CI runs)
#   make test-fast - the suite without the tests marked slow (under a minute; docs/testing.md)
# Extra arguments: make demo ARGS="--duration 10 --json"

PYTHON ?= python3
# Python keeps each module's compiled bytecode next to it and reuses it at the next start. Images
# that set PYTHONDONTWRITEBYTECODE (many do) make every process compile everything it imports
# again: torch alone took 4.0 s of CPU to import instead of 2.3, aiortc 0.8 instead of 0.4, and
# the suite and the demo start hundreds of processes. The venv is ours to write to.
unexport PYTHONDONTWRITEBYTECODE
VENV ?= .venv
BIN := $(VENV)/bin
# The CPU build this project is tested with; the range in pyproject.toml admits it. PyTorch's
# CPU-only wheels come from its own index: PyPI's Linux wheel is the CUDA build, gigabytes the
# tests never use. A wheel pip finds without an index (find-links: PIP_FIND_LINKS, pip.conf, a
# wheelhouse) is taken first. For the CUDA build (training on a GPU), name its index, e.g.
# make setup TORCH_INDEX=https://download.pytorch.org/whl/cuXXX, XXX the CUDA version the driver
# supports (pytorch.org names them; a setup already done: make clean first).
TORCH ?= torch==2.13.0
TORCH_INDEX ?= https://download.pytorch.org/whl/cpu
STAMP := $(VENV)/.installed

# Five lanes (docs/testing.md). The tests not marked slow run four at a time (pytest-xdist),
# each file on one worker so a module's fixture runs once; some of them bound a watchdog or a
# deadman by the product's limits, so they run in the lanes' group like every timed test. The slow
# ones marked `untimed` (they check no timing) run two at a time beside the timed lanes that
# follow (below). The other slow ones start deployments (nodes, simulators, browsers, fault
# cells) and bound their timing by the product's own limits (the 400 ms stop, the 150 ms
# staleness, a link simulator's floor), which must hold beside other deployments as on a busy
# robot PC: three at a time (four left the machine a quarter idle, gained little on a clean clone
# and failed browser jogs once, and a fault cell's controller starved past its watchdog).
# Those marked `serial` need a machine no deployment lane keeps busy (a page's video, the robot's
# heartbeats): two at a time, which mostly wait. Three took the lane from 125 s to 90 s, but the
# simulated lab's world fell behind real time (to 0.65 of it quiet) and, beside two busy loops, an
# assisted grasp turned the pipette past 90 degrees: the simulated lab wants a core. So do
# those marked `pty` (a driver against its simulator through a pseudo-terminal, within reply
# windows): the kernel's workers that carry a pty's bytes starve while the other lanes keep both
# cores busy (below). The alone lane runs one test at a time.
FAST_WORKERS ?= 4
DEPLOYMENT_WORKERS ?= 3
SERIAL_WORKERS ?= 2
# The lanes run above the machine's ordinary work (a CI machine's other jobs), in a session of
# their own: the deployments they start stand for robot PCs, controllers and boards of their own,
# and their budgets (the 400 ms stop, the 150 ms staleness) are the product's. The session's group
# takes the CPU before other sessions (group nice -20, about 87 times a session at nice 0); inside
# it the tests' own processes run at nice -5, below the nodes and the simulated hardware (-10).
# The cost: the kernel's workers that carry a pseudo-terminal's bytes (every simulated serial
# device's) run at nice 0 outside any session and get little while the lanes are busy
# (scripts/pty-latency-under-load.py); at -10 the busy loops reached the lanes more often.
# Where the user may not raise a priority, the lanes run at the one they have, and say so
# (scripts/at-test-priority.py, docs/testing.md).
TEST_NICE ?= -5
TEST_GROUP_NICE ?= -20
AT_TEST_PRIORITY := $(BIN)/python scripts/at-test-priority.py $(TEST_NICE) --group $(TEST_GROUP_NICE) --
# The untimed lane runs beside the timed lanes, in a group that takes about a hundredth of the
# CPU while they want it all (group nice 0 against their -20) and, on a machine whose other jobs
# keep it busy, a share of what the timed lanes leave like any other session; once they are done,
# it gets their weight. One after another, the lanes left 380 of the suite's 1070 core-seconds
# idle. At group nice -10 (a tenth) the deployment lane took 10-30 s longer, and in one quiet run
# a stop came late beside it; the tests not marked slow did not belong beside them at all: four
# of them bound a deadman or a watchdog, and failed there.
BESIDE_GROUP_NICE ?= 0
UNTIMED_WORKERS ?= 2
AT_BESIDE_PRIORITY := $(BIN)/python scripts/at-test-priority.py $(TEST_NICE) \
	--group $(BESIDE_GROUP_NICE) --then-group $(TEST_GROUP_NICE) --
UNTIMED_LANE_LOG := $(VENV)/untimed-lane.log
# The setup's collection writes which markers each test file's tests carry (tests/conftest.py);
# each lane's workers then import only the files that hold a test of the lane's -m, not all of
# them: every worker of every lane collected all 180 files for the 4 of the alone lane, the 20 of
# the serial lane. Without the index (a collection that failed writes none), every file.
TEST_INDEX := $(VENV)/test-index.json
LANE := $(AT_TEST_PRIORITY) $(BIN)/python -m pytest --test-index=$(TEST_INDEX)
# Whole files to each worker (a module's deployment starts once), the longest first
# (tests/file_durations.json, in tests/conftest.py's order; scripts/file-durations.py)
BY_FILE := --dist loadfile --no-loadscope-reorder
QUICK_LANE := not slow and not serial and not pty and not soak and not alone
UNTIMED_LANE := slow and untimed and not serial and not pty and not soak and not alone
DEPLOYMENT_LANE := slow and not untimed and not serial and not pty and not soak and not alone
SERIAL_LANE := (serial or pty) and not soak and not alone
# Several machines' deployments on one (a fleet: robots, operators, a router, an attacker) or a
# flood whose sender takes a core: beside any other lane's work they judged the machine
ALONE_LANE := alone and not soak

.PHONY: demo test test-fast lint bench setup clean

setup: $(STAMP)

# --no-compile: Python compiles a module the first time it is imported and keeps it; compiling
# every file of every package up front took 31 of the install's 58 s here.
# torch first, with pip, so the range in pyproject.toml installs nothing more: a wheel at hand
# without an index (its dependencies come with the project's, next), else TORCH_INDEX's.
# The project and its other dependencies with uv (installed into the venv by pip), from the
# indexes, wheel folders and constraints pip is configured with (scripts/pip-config-as-uv-args.py):
# pip took 58 s to resolve and unpack them, uv 9 to 11 (its cache cold). Where uv cannot, pip.
UV ?= uv>=0.5,<1
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -qq --no-compile --no-index --no-deps "$(TORCH)" 2>/dev/null \
		|| $(BIN)/python -m pip install -qq --no-compile "$(TORCH)" --index-url "$(TORCH_INDEX)"
	{ $(BIN)/python -m pip install -qq --no-compile "$(UV)" \
		&& $(BIN)/uv pip install -q --python $(BIN)/python \
			$$($(BIN)/python scripts/pip-config-as-uv-args.py) -e ".[all]"; } \
		|| $(BIN)/python -m pip install -qq --no-compile -e ".[all]"
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/deepxpalm demo $(ARGS)

test: $(STAMP)
	@# chromium (browser tests), Mesa's EGL (the lab's camera), coturn (video through TURN):
	@# required in CI, optional elsewhere
	bash scripts/install-test-system-packages.sh || [ -z "$$CI" ]
	@# LeRobot's own dataset class in an environment of its own (cached), to load exports with
	$(BIN)/python tests/export/lerobot_env.py || [ -z "$$CI" ]
	@# the robot node's numba code, the bytecode of the heavy packages and pytest's rewrite
	@# of every test module, compiled once (about 14, 13 and 5 s cold), not by every worker
	@# and every process it starts at once; the collection writes the lanes' test index. The
	@# numba warm-up is the shorter: the collection takes its core when it ends.
	rm -f $(TEST_INDEX)
	$(AT_TEST_PRIORITY) $(BIN)/python scripts/warm-bytecode.py & bytecode=$$!; \
	$(AT_TEST_PRIORITY) $(BIN)/python -m robot_side.node.jit_warm; jit=$$?; \
	{ $(AT_TEST_PRIORITY) $(BIN)/python -m pytest -q --collect-only -p no:cacheprovider \
		--write-test-index=$(TEST_INDEX) >/dev/null \
		|| echo "collection failed: the lanes below report why"; }; \
	wait $$bytecode && [ $$jit -eq 0 ]
	@# every lane runs whatever the one before gave; exit 5 is a lane that ARGS left empty. The
	@# untimed lane runs beside the timed ones (its report follows theirs), then takes their weight
	status=0; \
	$(LANE) -m "$(QUICK_LANE)" -n $(FAST_WORKERS) $(BY_FILE) $(ARGS) || [ $$? -eq 5 ] || status=1; \
	$(AT_BESIDE_PRIORITY) $(BIN)/python -m pytest --test-index=$(TEST_INDEX) \
		-m "$(UNTIMED_LANE)" -n $(UNTIMED_WORKERS) $(BY_FILE) $(ARGS) >$(UNTIMED_LANE_LOG) 2>&1 & \
	beside=$$!; \
	$(LANE) -m "$(DEPLOYMENT_LANE)" -n $(DEPLOYMENT_WORKERS) $(BY_FILE) $(ARGS) || [ $$? -eq 5 ] || status=1; \
	$(LANE) -m "$(SERIAL_LANE)" -n $(SERIAL_WORKERS) $(BY_FILE) $(ARGS) || [ $$? -eq 5 ] || status=1; \
	$(LANE) -m "$(ALONE_LANE)" -n 0 $(ARGS) || [ $$? -eq 5 ] || status=1; \
	kill -USR1 $$beside 2>/dev/null; \
	wait $$beside || [ $$? -eq 5 ] || status=1; \
	echo "the untimed lane (beside the others):"; cat $(UNTIMED_LANE_LOG); \
	exit $$status

# The fast lane: the quick lane's tests with the quick pty ones, none marked serial (a test that
# needs the machine to itself is not one for the edit-and-test loop), without the system
# packages the browser and TURN tests need (those tests are slow ones); under a minute. The whole
# suite stays `make test`.
test-fast: $(STAMP)
	$(BIN)/python -m pytest -m "not slow and not serial and not soak" -n $(FAST_WORKERS) $(ARGS)

bench: $(STAMP)
	$(BIN)/deepxpalm bench $(ARGS)

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

clean:
	rm -rf $(VENV) build *.egg-info
