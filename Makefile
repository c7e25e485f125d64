# Set-up-and-go targets.  `make demo` runs the controller against the emulated rig on the
# built-in defaults; `make test` runs the whole test suite (what CI runs via .ci/run).
# Both create the virtual environment and install everything they need on first use.
# EXTRAS: the optional dependencies installed with it (pyproject.toml); `make
# .venv/.installed-stamp EXTRAS=` installs the service alone (docs/deploy.md).

VENV ?= .venv
EXTRAS ?= dev,export
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp

.PHONY: demo test test-fast socketcan lint bench clean

$(STAMP): pyproject.toml
	python3 -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.$(if $(EXTRAS),[$(EXTRAS)])'
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/rig demo

test: $(STAMP)
	bash scripts/ensure-debian-packages.sh
	$(VENV)/bin/ruff check .
	$(VENV)/bin/mypy
	$(VENV)/bin/lint-imports
	$(PY) -m pytest -n 2 --timeout 600 -q
	bash tests/socketcan/run.sh

test-fast: $(STAMP)
	$(PY) -m pytest -n 2 -q -m "not slow"

socketcan: $(STAMP)
	bash tests/socketcan/run.sh

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/mypy
	$(VENV)/bin/lint-imports

bench: $(STAMP)
	$(PY) -m bench

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache
