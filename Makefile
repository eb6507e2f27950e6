# Two entry points for a fresh machine: `make demo` (main job) and `make test`.
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install demo test lint bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/cupnet demo

test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/python -m pytest

bench: $(STAMP)
	$(BIN)/python -m benchmarks.numsim
	$(BIN)/python -m benchmarks.solver_speed
	$(BIN)/python -m benchmarks.synth
	$(BIN)/python -m benchmarks.model
	$(BIN)/python -m benchmarks.predict

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
