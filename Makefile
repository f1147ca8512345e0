# Two commands do everything on a fresh machine with Python 3.11:
#   make demo   create .venv, install, run the whole loop on sample_data/, write the report
#   make test   same set-up, then ruff and the test suite (slow tests: make test-slow)
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
DEMO := demo

.PHONY: setup demo test test-slow lint bench reproduce reproduce-suite reproduce-quick clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; assert sys.version_info >= (3, 11), "bams-cli needs Python >= 3.11, found " + sys.version.split()[0]'
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev,dask]'
	@touch $(STAMP)

demo: $(STAMP)
	@PATH="$(CURDIR)/$(BIN):$$PATH" bash scripts/demo.sh $(DEMO)

# Installs nothing outside .venv: the report's browser test skips without Chromium
# (.ci/run installs it and makes its absence a failure).
# Two workers (pytest-xdist): CI has 2 cores, and most tests wait on one process at a time.
# BLAS pinned to one thread per worker so that two workers do not fight over two cores.
PYTEST := OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 $(BIN)/python -m pytest -n 2

test: $(STAMP)
	$(BIN)/ruff check .
	$(PYTEST) -q -m "not slow"

test-slow: $(STAMP)
	$(PYTEST) -q -m slow

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy bams_cli

# The paper's experiments through the same code a user runs (docs/reproduction/).
reproduce: $(STAMP)
	$(BIN)/bams-cli benchmark --protocol toy2d --seeds 10 --out docs/reproduction
	$(BIN)/bams-cli benchmark --protocol av_like --seeds 10 --out docs/reproduction/av_like
	$(MAKE) reproduce-suite

# The suite of unlike problems (core/suite.py) beside toy2d and av_like: suite.md over all.
reproduce-suite: $(STAMP)
	$(BIN)/bams-cli benchmark --protocol suite --seeds 10 --out docs/reproduction/suite

# Three seeds of the synthetic protocol, written outside docs/ (part of CI).
reproduce-quick: $(STAMP)
	$(BIN)/bams-cli benchmark --protocol toy2d --quick --out build/reproduction-quick

bench: $(STAMP)
	@for b in bench/bench_*.py; do echo "== $$b"; $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) $(DEMO) .pytest_cache .ruff_cache .mypy_cache
