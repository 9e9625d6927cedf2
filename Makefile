# tether: `make demo` and `make test` set everything up on a fresh machine.
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
export OPENBLAS_NUM_THREADS := 1
export MUJOCO_GL ?= egl
export PYOPENGL_PLATFORM ?= egl

# Debian packages: Mesa's EGL for offscreen rendering without a GPU; chromium
# (/usr/bin/chromium) for the tuning page's browser tests, driven by the
# playwright Python package (never `playwright install`); xvfb (/usr/bin/Xvfb), an
# X server without a screen, for the test of `tether view` (MuJoCo's GLFW viewer).
APT_PACKAGES := libegl1 libegl-mesa0 libgl1-mesa-dri libgles2
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)

.PHONY: demo test test-all wheel-check bench system-deps clean

system-deps:
	@if ! ldconfig -p | grep -q 'libEGL_mesa.so.0'; then \
	  echo "installing EGL/Mesa ($(APT_PACKAGES))"; \
	  $(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq $(APT_PACKAGES) >/dev/null; \
	fi
	@if [ ! -x /usr/bin/Xvfb ]; then \
	  echo "installing xvfb (Debian package) for the MuJoCo viewer's test (tether view)"; \
	  $(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq xvfb >/dev/null; \
	fi
	@if [ ! -x /usr/bin/chromium ]; then \
	  echo "installing chromium (Debian package) for the tuning page's browser tests"; \
	  $(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq chromium >/dev/null; \
	fi

# PYTHONWARNINGS: setuptools' "Editable installation" notice (folders named like
# a package in the working folder take precedence on import) is information.
$(STAMP): pyproject.toml
	python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	PYTHONWARNINGS='ignore:Editable installation' $(PY) -m pip install -q -e '.[test]'
	touch $(STAMP)

# The continuous-connectivity method (Nestmeyer et al. 2017) in the office, long enough for the
# first travelers to leave the start cluster and reach targets while the rest keep them connected.
DEMO_DURATION_S ?= 25
demo: system-deps $(STAMP)
	$(VENV)/bin/tether run connected-office --duration $(DEMO_DURATION_S) --video --rrd --out runs/demo

# The default suite skips tests marked slow so it stays well inside CI's budget.
test: system-deps $(STAMP)
	$(PY) -m pytest -q -m "not slow"

test-all: system-deps $(STAMP)
	$(PY) -m pytest -q

# Builds the sdist and wheel, installs the wheel into a fresh venv and runs the
# tether script from outside the repo (tests/test_wheel.py; CI runs it after test).
wheel-check: system-deps $(STAMP)
	$(PY) -m pytest -q -s tests/test_wheel.py

bench: system-deps $(STAMP)
	$(PY) bench/bench_core.py

clean:
	rm -rf runs .pytest_cache
