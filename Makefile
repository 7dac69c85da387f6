# Two commands do the whole set-up on a fresh machine (see README):
#   make demo   installs, then renders, simulates, reconstructs and scores a quick benchmark
#   make test   installs, then runs the default test suite
VENV ?= .venv
PY := $(VENV)/bin/python
OUT ?= runs/quick

.PHONY: setup demo test test-all bench-recon clean

setup:
	bash scripts/setup.sh

demo: setup
	$(VENV)/bin/capssim bench --suite quick -o $(OUT)

test: setup
	$(PY) -m pytest -q

test-all: setup
	$(PY) -m pytest -q -m "slow or not slow"

clean:
	rm -rf runs .pytest_cache
