# volwarp: make demo | make test | make bench | make lint | make examples
# Every target installs what it needs into .venv first; nothing else is assumed.
#
# Two installs into the one .venv, each with its own stamp:
#   make install (make demo, make examples): volwarp with its DICOM and Dask/OME-Zarr
#     extras, `.[dicom,scale]`; no system package (volwarp renders without OpenGL).
#   make install-test (make test, make bench, make lint): the test extras, `.[test]` (the
#     peers the suite and the benchmarks check against: about 2 GB), and, as root on
#     Debian, Mesa's EGL and Chromium for the checks that need them.
# Running one after the other adds what is missing to the same .venv: no reinstall.
# make test also installs .venv-peers (make install-peers): ANTs and elastix, whose
# antspyx pins numpy and scipy below volwarp's, for the tests of `volwarp apply` against
# them (tests/peers/; about 2 GB, 35 s).
# Both then compile and cache every numba kernel (python -m volwarp_cli.warmup, about a
# minute on a fresh install; again only when the package's sources change), so that no
# command, demo, test or cron job pays a kernel's compilation (3-7 s each) on its first run;
# the warm-up also keeps volwarp's dataclass methods compiled (volwarp_cli/dataclass_code.py).

PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
DEMO   ?= demo-output
DEMO_STAMP := $(VENV)/.installed-demo
TEST_STAMP := $(VENV)/.installed-test
PEERS_VENV ?= .venv-peers
PEERS_STAMP := $(PEERS_VENV)/.installed
# what a change of reinstalls: the package's metadata and the C modules compiled at install
INSTALLED_FROM := pyproject.toml $(wildcard volwarp_cli/*/*.c)
export VTK_DEFAULT_OPENGL_WINDOW ?= vtkEGLRenderWindow
# The compiled kernels: where the commands themselves keep them (volwarp_cli/entry.py: the
# package's __pycache__ folders, writable here), so that make's runs and direct runs of
# .venv/bin/volwarp share them. A NUMBA_CACHE_DIR of the caller's own is passed through.
WARM_STAMP := $(VENV)/.warmed-kernels
WARM_SOURCES := $(shell find volwarp_cli -name '*.py' 2>/dev/null)
# The package's bytecode, written ahead (only changed modules are recompiled): where
# PYTHONDONTWRITEBYTECODE is set, as on this project's CI machines, Python would
# otherwise compile every module it imports in every command (~0.08 s of a warp),
# and the editable install's finder, which every start-up imports before any volwarp code.
BYTECODE = $(BIN)/python -m compileall -q volwarp_cli && $(BIN)/python -c \
  "import compileall, glob, sysconfig; [compileall.compile_file(f, quiet=1) for f in glob.glob(sysconfig.get_paths()['purelib'] + '/__editable__*.py')]"

.PHONY: install install-test install-peers system-deps system-deps-render system-deps-browser \
        demo test bench lint examples clean

install: $(DEMO_STAMP)
	@$(MAKE) --no-print-directory $(WARM_STAMP)

install-test: $(TEST_STAMP)
	@$(MAKE) --no-print-directory $(WARM_STAMP)

# every numba kernel compiled and cached, with the signatures the commands use (after an
# install: the recipes below call it once theirs is done)
$(WARM_STAMP): $(WARM_SOURCES) $(INSTALLED_FROM)
	$(BIN)/python -m volwarp_cli.warmup
	touch $@

# the virtual environment itself, once
$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip

$(DEMO_STAMP): $(INSTALLED_FROM) | $(BIN)/python
	$(BIN)/pip install --quiet -e '.[dicom,scale]'
	$(BYTECODE)
	touch $@

# the test extras include the demo's (volwarp-cli[dicom,scale]): one install stamps both
$(TEST_STAMP): $(INSTALLED_FROM) | $(BIN)/python
	@$(MAKE) --no-print-directory system-deps
	$(BIN)/pip install --quiet -e '.[test]'
	$(BYTECODE)
	touch $@ $(DEMO_STAMP)

# ANTs and elastix, the peers `volwarp apply` is checked against, in an environment of
# their own (antspyx pins numpy and scipy below volwarp's): tests/peers/
install-peers: $(PEERS_STAMP)

$(PEERS_STAMP): tests/peers/requirements.txt
	$(PYTHON) -m venv $(PEERS_VENV)
	$(PEERS_VENV)/bin/pip install --quiet --upgrade pip
	$(PEERS_VENV)/bin/pip install --quiet -r tests/peers/requirements.txt
	touch $@

system-deps: system-deps-render system-deps-browser

# Mesa's software EGL (no display, no GPU), for what renders through VTK's OpenGL: the
# test suite's pyvista cross-checks and the benchmarks' VTK peers. volwarp's own renders
# (mesh --render, morph --render-to, sweep --render, the demo) need no OpenGL.
# Installed when missing and we are allowed to: make test only.
system-deps-render:
	@if ldconfig -p 2>/dev/null | grep -q 'libEGL_mesa.so.0' && ls /usr/lib/*/dri/swrast_dri.so >/dev/null 2>&1 \
	    && ldconfig -p | grep -q 'libGL.so.1' && ldconfig -p | grep -q 'libglib-2.0.so.0'; then \
	  :; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	  echo "installing Mesa EGL for the tests' and benchmarks' VTK renders, libGL and GLib for rt-utils' OpenCV"; \
	  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libegl1 libegl-mesa0 libgl1-mesa-dri libgl1 libglib2.0-0 >/dev/null; \
	else \
	  echo "warning: libEGL/Mesa not found and cannot install it: VTK's renders in the tests will fail" >&2; \
	fi

# Chromium checks the batch HTML report in a real browser (the test skips without one):
# Debian's, best effort, as root: make test only.
system-deps-browser:
	@if ! command -v chromium >/dev/null && [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	  echo "installing Chromium for the HTML report's browser test"; \
	  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null) \
	    || echo "warning: Chromium not installed: the report's browser test is skipped" >&2; \
	fi

# (the venv's bin first on PATH: scripts/demo.sh finds it there whether VENV is relative or
# absolute)
demo: $(DEMO_STAMP)
	$(BYTECODE)
	@$(MAKE) --no-print-directory $(WARM_STAMP)
	PATH=$(abspath $(BIN)):$$PATH DEMO=$(DEMO) BIN=$(BIN) bash scripts/demo.sh

# one pytest worker per core this process may use (affinity, cgroup quota), at most 8
# (each worker holds its own numpy/VTK/dask); a test file runs in one worker
TEST_WORKERS ?= $(shell $(BIN)/python -c "from volwarp_cli.parallel import available_cores as c; print(min(c(), 8))")

test: $(TEST_STAMP) $(PEERS_STAMP)
	$(BYTECODE)
	@$(MAKE) --no-print-directory $(WARM_STAMP)
	VOLWARP_PEERS_PYTHON=$(abspath $(PEERS_VENV))/bin/python VOLWARP_REQUIRE_PEERS=1 \
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile --durations=20

bench: $(TEST_STAMP)
	$(BYTECODE)
	@$(MAKE) --no-print-directory $(WARM_STAMP)
	$(BIN)/python benchmarks/run.py

lint: $(TEST_STAMP)
	$(BIN)/ruff check volwarp_cli tests benchmarks examples

examples: $(DEMO_STAMP)
	$(BYTECODE)
	@$(MAKE) --no-print-directory $(WARM_STAMP)
	PATH=$(CURDIR)/$(BIN):$$PATH $(MAKE) -C examples

clean:
	rm -rf $(DEMO) .pytest_cache .numba-cache $(WARM_STAMP)
