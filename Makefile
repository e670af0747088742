# Two commands set up and run everything on a fresh machine (Python 3.11):
#   make demo    - both nodes, simulated devices, the link simulator, a live view
#   make test    - the whole test suite (what CI runs)
#   make test-fast - the suite without the tests marked slow (under 3 minutes; README.md)
# Extra arguments: make demo ARGS="--duration 10 --json"

PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
# The CPU build this project is tested with; the range in pyproject.toml admits it.
TORCH ?= torch==2.13.0
STAMP := $(VENV)/.installed

# The tests not marked slow wait far more than they compute (25 s of CPU in 84 s on 2 cores),
# so they run four at a time (pytest-xdist: 41 s), with the slow ones marked untimed (no
# timing checked), each file on one worker so a module's fixture runs once. The other slow
# ones run one at a time: their timing checks compare with baselines taken in the same run,
# under the machine's own load; so do the few quick ones marked serial (their timing checks
# skip on a loaded machine, and in the parallel lane their neighbours are the load).
FAST_WORKERS ?= 4

.PHONY: demo test test-fast lint bench setup clean

setup: $(STAMP)

# --no-compile: Python compiles a module the first time it is imported and keeps it; compiling
# every file of every package up front took 31 of the install's 58 s here.
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -qq --no-compile "$(TORCH)"
	$(BIN)/python -m pip install -qq --no-compile -e ".[all]"
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/deepxpalm demo $(ARGS)

test: $(STAMP)
	@# chromium (browser tests), Mesa's EGL (the lab's camera), coturn (video through TURN):
	@# required in CI, optional elsewhere
	bash scripts/install-test-system-packages.sh || [ -z "$$CI" ]
	@# LeRobot's own dataset class in an environment of its own (cached), to load exports with
	$(BIN)/python tests/export/lerobot_env.py || [ -z "$$CI" ]
	@# both lanes run whatever the first gave; exit 5 is a lane that ARGS left empty
	status=0; \
	$(BIN)/python -m pytest -m "(not slow or untimed) and not serial and not soak" -n $(FAST_WORKERS) --dist loadfile $(ARGS) || [ $$? -eq 5 ] || status=1; \
	$(BIN)/python -m pytest -m "(slow and not untimed or serial) and not soak" $(ARGS) || [ $$? -eq 5 ] || status=1; \
	exit $$status

# The fast lane: every test not marked slow, without the system packages the browser and
# TURN tests need (those tests are slow ones). The whole suite stays `make test`.
test-fast: $(STAMP)
	status=0; \
	$(BIN)/python -m pytest -m "not slow and not serial and not soak" -n $(FAST_WORKERS) $(ARGS) || [ $$? -eq 5 ] || status=1; \
	$(BIN)/python -m pytest -m "serial and not slow and not soak" $(ARGS) || [ $$? -eq 5 ] || status=1; \
	exit $$status

bench: $(STAMP)
	$(BIN)/deepxpalm bench $(ARGS)

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

clean:
	rm -rf $(VENV) build *.egg-info
