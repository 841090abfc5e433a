# colony: set-up, demo and tests. Every target creates .venv on a machine that has only Python.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test fuzz bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test,bench,ros]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/colonyd demo --out demo-out

test: $(STAMP)
	$(BIN)/python -m pytest -q --durations=15 tests

fuzz: $(STAMP)
	COLONY_FUZZ_CASES=100000 $(BIN)/python -m pytest -q tests/protocol/test_fuzz.py

bench: $(STAMP)
	$(BIN)/colonyd bench integrate --json docs/bench-integrate.json

clean:
	rm -rf $(VENV) demo-out
