# Two commands do everything on a fresh machine:
#   make demo   set up, then run the main job on an embedded synthetic capture
#   make test   set up, lint (ruff + mypy), then run the whole test suite
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
APT_PACKAGES := libusb-1.0-0 libgomp1 redis-server libllvm19
DEMO_OUT ?= demo-out

.PHONY: setup system-packages demo lint test bench clean

setup: system-packages $(STAMP)

# System packages (open3d needs libusb; the service tests need redis-server).
# Installed only when missing, with apt-get as root.
system-packages:
	@missing=""; for p in $(APT_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  echo "installing system packages:$$missing"; \
	  if [ "$$(id -u)" = 0 ]; then apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing; \
	  else sudo apt-get update -qq && sudo DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing; fi; \
	fi

# torch is pinned to the CPU build (pyproject); the install is redone when pyproject changes.
$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[service,dev,mitsuba]'
	touch $(STAMP)

demo: setup
	$(PY) -m service.demo --out $(DEMO_OUT)

# ruff (rules and complexity limit in pyproject.toml) and mypy on the library and the service.
lint: setup
	$(PY) -m ruff check pmvir service tests bench conftest.py
	$(PY) -m mypy

test: setup lint
	$(PY) -m pytest -q

bench: setup
	$(PY) bench/demosaic.py

clean:
	rm -rf $(VENV) $(DEMO_OUT) .pytest_cache .ruff_cache .mypy_cache
