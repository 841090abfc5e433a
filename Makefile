# colony: set-up, demo and tests. Every target creates .venv on a machine that has only Python.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test lint fuzz bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test,bench,ros,fast]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/colonyd demo --out demo-out

test: $(STAMP)
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
