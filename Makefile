# Everything a fresh machine needs is installed from here (Python 3.11 venv at .venv/).
PYTHON ?= python3.11
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: setup test test-fast demo bench clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test]'
	touch $(STAMP)

# The README's test command; CI runs exactly this. loadgroup keeps the flow tests on one
# worker: one embedded Prefect server and one calibration cache instead of two.
test: setup
	$(BIN)/python -m pytest -n 2 --dist loadgroup -q --durations=15

test-fast: setup
	$(BIN)/python -m pytest -n 2 --dist loadgroup -q -m "not slow"

demo: setup
	$(BIN)/mscal demo

# Figures into docs/benchmarks.md, each beside its baseline measured in the same run.
bench: setup
	$(BIN)/python bench/bench_calibrate.py --seeds 0 1 2
	$(BIN)/python bench/bench_apply.py --frames 600 --large 2400

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
