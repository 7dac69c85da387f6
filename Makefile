# Two commands do the whole set-up on a fresh machine (see README):
#   make demo   installs, then renders, simulates, reconstructs and scores a quick benchmark
#   make test   installs, then runs the default test suite
VENV ?= .venv
PY := $(VENV)/bin/python
OUT ?= runs/quick
# pytest workers for `make test` (pytest-xdist); 2 matches the 2-core CI machines
TEST_WORKERS ?= 2

.PHONY: setup demo test test-processes test-all lint docs bench-check results-page bench-recon clean

setup:
	bash scripts/setup.sh

demo: setup
	$(VENV)/bin/capssim bench suite quick -o $(OUT)

# benchmarks (capssim bench SUBJECT; see `capssim bench --help`)
bench-check: setup
	$(VENV)/bin/capssim bench suite quick -o runs/ci-quick --check eval/baselines/quick.json

results-page: setup
	$(VENV)/bin/capssim bench suite quick -o $(OUT) --results-page docs/results/quick.md

bench-recon: setup
	$(VENV)/bin/capssim bench reconstruct --size 256 --size 512 --repeats 3

test: setup
	$(PY) -m pytest -q -n $(TEST_WORKERS)

# the tests that kill, resume or spread whole commands over Dask clusters (CI runs them after `make test`)
test-processes: setup
	$(PY) -m pytest -q -n $(TEST_WORKERS) -m processes

test-all: setup
	$(PY) -m pytest -q -n $(TEST_WORKERS) -m "slow or not slow"

# ruff: pyflakes and import sorting (pyproject.toml [tool.ruff])
lint: setup
	$(VENV)/bin/ruff check .

# the documentation site, built strictly into site/ (a broken link or reference fails)
docs: setup
	PATH="$(CURDIR)/$(VENV)/bin:$$PATH" bash scripts/build-docs.sh

clean:
	rm -rf runs site .pytest_cache
