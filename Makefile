# Two entry points, both set-up-free on a fresh machine: `make demo` and `make test`.
# The virtual environment is built on first use. torch is pinned to the local CPU build
# first, so that no dependency pulls the multi-GB CUDA wheels.
PY := .venv/bin/python
TORCH := torch==2.13.0

.venv/ready: pyproject.toml
	python3 -m venv .venv
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q $(TORCH)
	$(PY) -m pip install -q -e ".[dev]"
	touch $@

.PHONY: demo test lint
demo: .venv/ready
	$(PY) -m segmo demo --out runs/demo

# The suite runs on JOBS worker processes (pytest-xdist; every CPU up to 4, `make test JOBS=1`
# for one): each test runs single-threaded, so a 2-core machine is used twice as well. Tests
# that start their own multi-process runs (DDP) share one worker (`xdist_group`).
JOBS ?= $(shell python3 -c "import os; n = len(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else os.cpu_count(); print(min(4, n or 1))")
test: .venv/ready
	$(PY) -m pytest -q -n $(JOBS) --dist loadgroup

lint: .venv/ready
	$(PY) -m ruff check segmo tests tools notebooks
