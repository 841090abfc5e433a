# colony: set-up, demo and tests. Every target creates .venv on a machine that has only Python.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: bytecode demo test lint fuzz bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test,bench,ros,fast]'
	touch $(STAMP)

# Byte-compile the packages before starting daemons: where PYTHONDONTWRITEBYTECODE is set (CI
# images often set it) every process would compile every module again, ~0.2 CPU-s each, and the
# tests start hundreds of daemons and command-line runs.
PACKAGES := colonyd voxel protocol plugins

bytecode: $(STAMP)
	$(BIN)/python -m compileall -q $(PACKAGES)

demo: bytecode
	$(BIN)/colonyd demo --out demo-out

test: bytecode
	$(BIN)/python -m pytest -q -n 2 --durations=15 tests

# Style: ruff's lint rules and formatting on the whole tree; mypy (strict on voxel and protocol,
# as pyproject.toml configures it) on every package.
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy voxel protocol
	$(BIN)/mypy colonyd plugins

fuzz: $(STAMP)
	COLONY_FUZZ_CASES=100000 $(BIN)/python -m pytest -q tests/protocol/test_fuzz.py

bench: $(STAMP)
	$(BIN)/colonyd bench integrate --json docs/bench-integrate.json

clean:
	rm -rf $(VENV) demo-out
