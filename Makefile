# Two commands do everything on a fresh machine (Python >= 3.10 with venv):
#   make run    set up .venv and run the default job (built-in synthetic sequence)
#   make test   set up .venv (with test extras) and run the test suite
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
# torch first, pinned: an unpinned torch pulls a multi-GB CUDA build on a CPU machine.
TORCH ?= torch==2.13.0
# Compiled extensions and generated data stay inside the project.
export TORCH_EXTENSIONS_DIR := $(CURDIR)/.cache/torch_extensions
export SLAMKIT_CACHE ?= $(CURDIR)/.cache/slamkit

.PHONY: run test setup setup-test clean

run: setup
	$(VENV)/bin/slamkit $(ARGS)

test: setup-test
	$(PY) -m pytest $(PYTEST_ARGS)

setup: $(VENV)/.installed
setup-test: $(VENV)/.installed-test

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip

$(VENV)/.torch: | $(PY)
	$(PY) -c "import torch" 2>/dev/null || $(PY) -m pip install --quiet "$(TORCH)"
	touch $@

$(VENV)/.installed: pyproject.toml $(VENV)/.torch
	$(PY) -m pip install --quiet -e .
	touch $@

$(VENV)/.installed-test: pyproject.toml examples/slamkit-p2plane/pyproject.toml $(VENV)/.torch
	$(PY) -m pip install --quiet -e ".[test]"
	$(PY) -m pip install --quiet --no-deps -e examples/slamkit-p2plane  # the example third-party plugin
	touch $(VENV)/.installed $@

clean:
	rm -rf $(VENV) .cache outputs multirun
