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

# Two passes (test/conftest.py): the computational modules spread over every core (pytest-xdist),
# then the modules with ROS nodes, node processes or forks, one test at a time.  Both passes run; the
# target fails when either does.  (pytest-rerunfailures, when a developer's environment has it, starts
# a thread in the main process that stops the fork tests: it is switched off.)
PYTEST := ROS_PYTHON_CHECK_FIELDS=1 $(PY) -m pytest -q -p no:cacheprovider -p no:rerunfailures

test: $(BYTECODE)
	@status=0; \
	$(PYTEST) -n auto --dist loadfile -m "not serial" test || status=1; \
	$(PYTEST) -m serial test || status=1; \
	exit $$status

bench: $(BYTECODE)
	$(PY) -m bench.run_all

clean:
	rm -rf $(VENV) build *.egg-info
