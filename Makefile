# democheck: set-up, demo and tests on a fresh Debian machine with Python 3.11.
#   make demo   - install, then run the main job
#   make test   - install, then run the default (fast) tests
#   make test-user  - as a user: the wheel installed in a fresh venv elsewhere runs the demo; the README's
#                     "audit your own dataset" walkthrough runs on a small foreign dataset
# Override the interpreter with `make PYTHON=python3.12 ...`.

PYTHON ?= python3
# pyproject.toml asks for torch>=2.4; installing this first keeps the set-up small where a CPU
# build of this version is at hand. `make TORCH=torch` lets pip choose (a CUDA build on Linux).
TORCH  ?= torch==2.13.0
VENV   ?= .venv
BIN    := $(VENV)/bin
SYSDEPS := libegl1 libegl-mesa0 libgl1-mesa-dri libopengl0
export MUJOCO_GL ?= egl

.PHONY: setup sysdeps demo test test-user bench clean

# Headless MuJoCo rendering needs EGL and Mesa; install them when missing and when we may.
sysdeps:
	@missing=""; \
	if command -v dpkg >/dev/null 2>&1; then \
	  for p in $(SYSDEPS); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	fi; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = 0 ]; then SUDO=""; elif sudo -n true 2>/dev/null; then SUDO="sudo"; else SUDO=none; fi; \
	  if [ "$$SUDO" = none ]; then \
	    echo "democheck: headless rendering needs:$$missing -- run: sudo apt-get install -y$$missing" >&2; \
	  else \
	    echo "installing$$missing"; \
	    $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq --no-install-recommends $$missing >/dev/null; \
	  fi; \
	fi

$(BIN)/activate:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip

# Re-install when the project's requirements change.
$(VENV)/.installed: pyproject.toml | $(BIN)/activate
	$(BIN)/pip install -q '$(TORCH)'
	$(BIN)/pip install -q -e '.[test]'
	@touch $@

setup: sysdeps $(VENV)/.installed

demo: setup
	$(BIN)/democheck demo --out demo --force

test: setup
	$(BIN)/python -m pytest -q

# Slow (about two minutes, and it downloads democheck's dependencies into the fresh venv): CI runs it after `test`.
test-user: setup
	DEMOCHECK_TORCH='$(TORCH)' $(BIN)/python -m pytest -q -m slow benchmarks/test_slow.py -k "wheel or walkthrough"

bench: setup
	$(BIN)/python benchmarks/synth_speed.py --repeats 3

clean:
	rm -rf $(VENV) *.egg-info .pytest_cache
