# Two commands for a fresh machine with Python 3.11: `make demo` and `make test`.
PYTHON ?= python3.11
VENV ?= .venv
BIN := $(VENV)/bin

.PHONY: demo test setup setup-dev lint lock clean

# The versions the tests run on (requirements/lock.py): every install takes them.
CONSTRAINTS := requirements/constraints.txt

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

# Runtime only (no torch): what the detector and the service need.
$(VENV)/.runtime: pyproject.toml $(CONSTRAINTS) | $(BIN)/python
	$(BIN)/pip install --quiet -e . -c $(CONSTRAINTS)
	touch $@

# Everything: runtime + training/export (torch pinned to the CPU build) + test tools.
$(VENV)/.dev: pyproject.toml $(CONSTRAINTS) | $(BIN)/python
	$(BIN)/pip install --quiet -e '.[train,dev]' -c $(CONSTRAINTS)
	touch $@ $(VENV)/.runtime

setup: $(VENV)/.runtime
setup-dev: $(VENV)/.dev

demo: $(VENV)/.runtime
	$(BIN)/python -m pipeline.demo --out outputs/demo

# Two pytest workers, a test file each at a time (its fixtures built once per worker): the suite's subprocesses,
# imports and servers leave a core idle in a serial run (12.2 against 7.9 min on a 2-vCPU Zen 3, session 17).
# The 15 slowest tests close the log: where the suite's time goes, run after run.
test: $(VENV)/.dev
	$(BIN)/python -m pytest -q -n 2 --dist loadfile --durations=15

lint: $(VENV)/.dev
	$(BIN)/ruff check pipeline service models export evaluation simulation benchmarks requirements tests
	$(BIN)/mypy

# After moving a dependency in the dev environment: pin what is installed now, then run make test.
lock: $(VENV)/.dev
	$(BIN)/python requirements/lock.py

clean:
	rm -rf $(VENV) outputs
