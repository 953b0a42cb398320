# The two commands (docs/interfaces.md, "Set-up"): `make demo` and `make test`.
# Each creates .venv/ on first use and installs everything into it; later runs reuse it.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp
BYTECODE := $(VENV)/.bytecode-stamp
SOURCES := $(shell find mpm_monitor -name '*.py')
export AMENT_PREFIX_PATH := $(abspath $(VENV))
export PYTHONDONTWRITEBYTECODE := 1

.PHONY: demo test bench venv clean

venv: $(BYTECODE)

$(STAMP): requirements.txt setup.py package.xml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --disable-pip-version-check --upgrade pip
	$(PY) -m pip install --quiet --disable-pip-version-check -r requirements.txt
	$(PY) -m pip install --quiet --disable-pip-version-check --no-deps --no-build-isolation -e .
	@touch $(STAMP)

# The package's bytecode, compiled once per change of its sources: the commands run with
# PYTHONDONTWRITEBYTECODE (as here), so nothing else writes it, and compiling some fifty modules
# on every start costs about 0.2 s.
$(BYTECODE): $(STAMP) $(SOURCES)
	$(PY) -m compileall -q mpm_monitor
	@touch $(BYTECODE)

demo: $(BYTECODE)
	$(PY) -m mpm_monitor demo --case 3.2

test: $(BYTECODE)
	ROS_PYTHON_CHECK_FIELDS=1 $(PY) -m pytest -q -p no:cacheprovider test

bench: $(BYTECODE)
	$(PY) -m bench.run_all

clean:
	rm -rf $(VENV) build *.egg-info
