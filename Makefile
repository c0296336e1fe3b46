# Everything a fresh machine needs is installed from here (Python 3.11 venv at .venv/).
PYTHON ?= python3.11
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: setup test test-long test-fast demo bench bench-quick clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test]'
	touch $(STAMP)

# The README's test command; CI runs exactly this. loadgroup keeps the flow tests on one
# worker: one embedded Prefect server and one calibration cache instead of two.
# ruff first (lint and import order: pyproject.toml, pipeline/ruff.toml), then the tests;
# the long versions of a few tests (many trials, full-size rigs) run with make test-long.
test: setup
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -n 2 --dist loadgroup -q --durations=15 -m "not long"

test-long: setup
	$(BIN)/python -m pytest -n 2 --dist loadgroup -q --durations=15 -m long

test-fast: setup
	$(BIN)/python -m pytest -n 2 --dist loadgroup -q -m "not slow and not long"

demo: setup
	$(BIN)/mscal demo

# Every generated section of docs/benchmarks.md (and the plots in docs/img/), each figure beside
# its baseline measured in the same run; < 30 min on the 2-core machine when it is quiet.
# Memory vs frames (formerly bench_apply --large) is in bench_scale's tables.
bench: setup
	$(BIN)/python bench/bench_calibrate.py --seeds 0 1 2 --varied 5
	$(BIN)/python bench/bench_apply.py --frames 600 --large 0
	$(BIN)/python bench/bench_factory.py --captures 1000
	$(BIN)/python bench/bench_accuracy.py --varied 10
	$(BIN)/python bench/bench_scale.py

# Smoke run of the same scripts at small sizes (< 5 min), into build/bench-quick/ so the
# published figures are not replaced.
BENCH_QUICK := build/bench-quick
bench-quick: setup
	mkdir -p $(BENCH_QUICK)
	$(BIN)/python bench/bench_calibrate.py --quick --out $(BENCH_QUICK)/benchmarks.md
	$(BIN)/python bench/bench_apply.py --frames 60 --large 0 --settle 0 --repeat 1 --out $(BENCH_QUICK)/benchmarks.md
	$(BIN)/python bench/bench_factory.py --quick --out $(BENCH_QUICK)/benchmarks.md
	$(BIN)/python bench/bench_accuracy.py --quick --out $(BENCH_QUICK)/benchmarks.md --img-dir $(BENCH_QUICK)/img
	$(BIN)/python bench/bench_scale.py --quick --out $(BENCH_QUICK)/benchmarks.md

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
