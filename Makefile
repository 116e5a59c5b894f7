# Every target creates/uses the virtual environment at .venv/ (nothing is installed system-wide).
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
SHARED ?= ../shared/data

DATASET ?= sample
ROOT ?= data/$(DATASET)
OUT ?= out/labels/$(DATASET)
JOBS ?= 2
PYTEST_ARGS ?=

.PHONY: install test test-faults test-slow test-all test-studies bench demo labels results lint clean

install: $(STAMP)

# torch is installed first with an exact pin so pip takes the local CPU wheel instead of a multi-GB CUDA build.
# --no-cache-dir: a fresh CI disk ran out of space (ENOSPC) holding the wheels twice, once in .venv, once in the cache.
$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --no-cache-dir --upgrade pip
	$(PY) -m pip install -q --no-cache-dir "torch==2.13.0"
	$(PY) -m pip install -q --no-cache-dir -e ".[dev]"
	touch $(STAMP)

test: $(STAMP)
	$(PY) -m pytest -q $(PYTEST_ARGS)

# The fault tests (SIGKILL + resume, a killed Dask worker, checkpoint kills, peak-RSS bounds): slow ones included.
# CI runs them after `make test` (.ci/run).
test-faults: $(STAMP)
	$(PY) -m pytest -q --runslow -m faults $(PYTEST_ARGS)

test-slow: $(STAMP)
	$(PY) -m pytest -q --runslow -m "slow or perf" $(PYTEST_ARGS)

test-all: $(STAMP)
	$(PY) -m pytest -q --runslow --studies $(PYTEST_ARGS)

# tests/studies (the one-off studies of pipelines/studies/): never collected by `make test`; PYTEST_ARGS=--runslow adds
# their slow cases
test-studies: $(STAMP)
	$(PY) -m pytest -q --studies tests/studies $(PYTEST_ARGS)

bench: $(STAMP)
	$(PY) -m pipelines.bench --shared $(SHARED) --out bench

labels: $(STAMP)
	$(VENV)/bin/pvm-label run --dataset $(DATASET) $(if $(filter sample,$(DATASET)),,--root $(ROOT)) --out $(OUT) --jobs $(JOBS)

demo: $(STAMP)
	$(PY) -m pipelines.demo --out out/demo

results: $(STAMP)
	$(PY) -m pipelines.results --shared $(SHARED) --out results

lint: $(STAMP)
	$(VENV)/bin/ruff check .

clean:
	rm -rf out .pytest_cache
