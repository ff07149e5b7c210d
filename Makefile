# Set-up on a fresh machine: `make train` installs the core and trains the default Cartpole;
# `make test` installs the `dev` set (every suite, lint, tests) and runs lint and the tests.
# Another Python: `make test PYTHON=python3.13 VENV=.venv-3.13` (each venv is its own); under pyenv,
# where `python3.13` runs only in a shell that selected it, name its path: PYTHON=$(pyenv prefix 3.13.0)/bin/python3.13.
PYTHON ?= $(shell for p in python3.11 python3.12 python3.13 python3; do $$p -c '' 2>/dev/null && command -v $$p && break; done)
VENV ?= .venv
# The suite's files spread over this many processes (pytest-xdist), a file's tests in one of them.
TEST_WORKERS ?= 2
PY := $(VENV)/bin/python

.PHONY: train test lint docs docs-serve benchmark wheel-check

$(VENV)/.created:
	@test -x $(PY) || $(PYTHON) -c '' 2>/dev/null || { \
		echo "make: PYTHON='$(PYTHON)' does not run; name a Python 3.11 to 3.13 that does, e.g. PYTHON=/usr/bin/python3.12" >&2; exit 2; }
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	touch $@

$(VENV)/.core: $(VENV)/.created pyproject.toml
	$(PY) -m pip install --quiet -e .
	touch $@

$(VENV)/.dev: $(VENV)/.created pyproject.toml
	$(PY) -m pip install --quiet -e '.[dev]'
	$(PY) -m pip check
	touch $@ $(VENV)/.core $(VENV)/.docs

# The docs need the core (the flag reference is read from its dataclasses) and the docs extra alone.
$(VENV)/.docs: $(VENV)/.created pyproject.toml
	$(PY) -m pip install --quiet -e '.[docs]'
	touch $@ $(VENV)/.core

train: $(VENV)/.core
	$(PY) -m rpo_jax.train

lint: $(VENV)/.dev
	$(VENV)/bin/ruff check rpo_jax tests benchmarks
	$(VENV)/bin/ruff format --check rpo_jax tests benchmarks
	$(VENV)/bin/lint-imports

# The site in site/, strict: a warning, a broken link or anchor fails the build.
docs: $(VENV)/.docs
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict --quiet

# The site at http://127.0.0.1:8000, rebuilt as the pages change.
docs-serve: $(VENV)/.docs
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs serve

test: lint docs
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile

# The built wheel, installed (not editable) into a fresh venv outside the source tree with the
# core's dependencies alone, lists its environments and trains the default Cartpole.
wheel-check:
	bash .ci/wheel-check $(PYTHON)

benchmark: $(VENV)/.dev
	$(PY) benchmarks/throughput.py --env cartpole --num-envs 1024
