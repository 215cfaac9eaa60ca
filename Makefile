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

test: .venv/ready
	$(PY) -m pytest -q

lint: .venv/ready
	$(PY) -m ruff check segmo tests tools
