# Set-up on a fresh machine: `make train` or `make test` creates .venv and installs rpo_jax.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
PY := $(VENV)/bin/python

.PHONY: train test lint benchmark

$(VENV)/.installed: pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $@

train: $(VENV)/.installed
	$(PY) -m rpo_jax.train

lint: $(VENV)/.installed
	$(VENV)/bin/ruff check rpo_jax tests benchmarks
	$(VENV)/bin/lint-imports

test: lint
	$(PY) -m pytest -q

benchmark: $(VENV)/.installed
	$(PY) benchmarks/throughput.py --env cartpole --num-envs 1024
