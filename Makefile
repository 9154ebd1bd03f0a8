# darp: two commands on a fresh machine.
#   make demo   set everything up, then run the main job on the embedded digital twin
#   make test   set everything up, then lint (ruff), type-check (mypy strict) and run the whole test suite
#   make bench  set everything up, then run the benchmarks (darp next to its peers): one table in .bench/

PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
DARP   := $(VENV)/bin/darp
STAMP  := $(VENV)/.darp-installed
export MUJOCO_GL ?= egl
export PYOPENGL_PLATFORM ?= egl

.PHONY: all setup vendor demo lint test test-fast bench clean

all: test

$(STAMP): pyproject.toml scripts/ensure_system_libs.sh
	@bash scripts/ensure_system_libs.sh
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "darp needs Python >= 3.11")'
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	@echo "installing darp and its Python dependencies into $(VENV) (about 6 minutes, once)"
	@$(PY) -m pip install -q --upgrade pip
	@$(PY) -m pip install -q -e '.[test,bench,ecosystem]'
	@touch $(STAMP)

setup: $(STAMP)

# Unitree's controller (simulated motors) and SDK binding for the vendor-in-the-loop tests: built once per
# venv, cached in $(VENV)/z1_vendor (exit 3: the vendor sources are not beside the repository, tests skip).
vendor: $(STAMP)
	@bash scripts/build_z1_vendor.sh $(PY) || [ $$? -eq 3 ]

demo: $(STAMP)
	$(DARP) demo

lint: $(STAMP)
	$(PY) -m ruff check src tests benchmarks studies scripts
	$(PY) -m mypy

test: lint vendor
	$(PY) -m pytest -n 2 --dist loadfile -q

test-fast: vendor
	$(PY) -m pytest -n 2 --dist loadfile -q -m "not slow"

bench: $(STAMP)
	$(PY) benchmarks/run.py

clean:
	rm -rf $(VENV) build dist src/*.egg-info .pytest_cache
