# volwarp: make demo | make test | make bench | make lint | make examples
# Every target installs what it needs into .venv first; nothing else is assumed.

PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
DEMO   ?= demo-output
export VTK_DEFAULT_OPENGL_WINDOW ?= vtkEGLRenderWindow
export NUMBA_CACHE_DIR ?= $(CURDIR)/.numba-cache
# The package's bytecode, written ahead (only changed modules are recompiled): where
# PYTHONDONTWRITEBYTECODE is set, as on this project's CI machines, Python would
# otherwise compile every module it imports in every command (~0.08 s of a warp),
# and the editable install's finder, which every start-up imports before any volwarp code.
BYTECODE = $(BIN)/python -m compileall -q volwarp_cli && $(BIN)/python -c \
  "import compileall, glob, sysconfig; [compileall.compile_file(f, quiet=1) for f in glob.glob(sysconfig.get_paths()['purelib'] + '/__editable__*.py')]"

.PHONY: install system-deps demo test bench lint examples clean

install: $(STAMP)

# the compiled warp kernels and the SIGBUS guard are built by the install: rebuild when they change
$(STAMP): pyproject.toml volwarp_cli/bspline/_warpkernels.c volwarp_cli/io/_mapguard.c
	@$(MAKE) --no-print-directory system-deps
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test]'
	$(BYTECODE)
	touch $@

# Headless rendering goes through Mesa's software EGL (no display, no GPU).
# Install the Debian packages when they are missing and we are allowed to.
# Chromium checks the batch HTML report in a real browser (the test skips without it).
system-deps:
	@if ldconfig -p 2>/dev/null | grep -q 'libEGL_mesa.so.0' && ls /usr/lib/*/dri/swrast_dri.so >/dev/null 2>&1; then \
	  :; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	  echo "installing Mesa EGL for headless rendering"; \
	  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libegl1 libegl-mesa0 libgl1-mesa-dri >/dev/null; \
	else \
	  echo "warning: libEGL/Mesa not found and cannot install it: renders will fail" >&2; \
	fi
	@# the batch report's browser test (skipped without one): Debian's Chromium, best effort
	@if ! command -v chromium >/dev/null && [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	  echo "installing Chromium for the HTML report's browser test"; \
	  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null) \
	    || echo "warning: Chromium not installed: the report's browser test is skipped" >&2; \
	fi

demo: $(STAMP)
	$(BYTECODE)
	DEMO=$(DEMO) BIN=$(BIN) bash scripts/demo.sh

# one pytest worker per core this process may use (affinity, cgroup quota), at most 8
# (each worker holds its own numpy/VTK/dask); a test file runs in one worker
TEST_WORKERS ?= $(shell $(BIN)/python -c "from volwarp_cli.parallel import available_cores as c; print(min(c(), 8))")

test: $(STAMP)
	$(BYTECODE)
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile --durations=20

bench: $(STAMP)
	$(BYTECODE)
	$(BIN)/python benchmarks/run.py

lint: $(STAMP)
	$(BIN)/ruff check volwarp_cli tests benchmarks examples

examples: $(STAMP)
	$(BYTECODE)
	PATH=$(CURDIR)/$(BIN):$$PATH $(MAKE) -C examples

clean:
	rm -rf $(DEMO) .pytest_cache .numba-cache
