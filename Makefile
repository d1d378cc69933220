# realgap: two commands do all set-up on a fresh Debian machine (run as root, or with sudo available).
#   make demo   - install what is missing, then run the main demo on embedded default data
#   make test   - install what is missing, then run the default test suite (slow tests: make test-slow)
SHELL := /bin/bash
PY ?= python3
VENV := .venv
VPY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
APT_PKGS := libusb-1.0-0 libgl1 libegl1 libgomp1
PYTEST_ARGS ?=

.PHONY: demo test test-slow bench setup sysdeps clean

setup: sysdeps $(STAMP)

# System libraries Open3D needs (USB for sensors, GL/EGL for rendering, OpenMP).
sysdeps:
	@missing=""; for p in $(APT_PKGS); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	$(PY) -c "import ensurepip, venv" >/dev/null 2>&1 || missing="$$missing python3-venv"; \
	if [ -n "$$missing" ]; then \
	  echo "installing system packages:$$missing"; \
	  SUDO=""; [ "$$(id -u)" != 0 ] && SUDO=sudo; \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq $$missing >/dev/null; \
	fi

$(STAMP): pyproject.toml
	@test -x $(VPY) || $(PY) -m venv $(VENV)
	@echo "installing Python dependencies into $(VENV) (first run only)"
	@set -o pipefail; { $(VPY) -m pip install -q --upgrade pip && \
	  $(VPY) -m pip install -q "torch==2.13.0" && \
	  $(VPY) -m pip install -q -e ".[dev]"; } 2>&1 | grep -v "is ignored: it is neither a file nor a directory" || true
	@$(VPY) -c "import open3d, torch, cv2, trimesh, pyvista, app.cli" || { echo "Python dependencies failed to install"; exit 1; }
	@touch $(STAMP)

demo: setup
	$(VENV)/bin/realgap demo --out demo_out

test: setup
	$(VPY) -m pytest -q $(PYTEST_ARGS)

test-slow: setup
	$(VPY) -m pytest -q --runslow $(PYTEST_ARGS)

bench: setup
	@for b in benchmarks/bench_*.py; do echo "== $$b"; $(VPY) $$b || exit 1; done

clean:
	rm -rf $(VENV) demo_out .pytest_cache
