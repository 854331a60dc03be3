# Two commands do everything on a fresh machine:
#   make demo   set up, then run the main job on an embedded synthetic capture
#   make test   set up, then run the whole test suite
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
NPM_DIR := service/static
NPM_STAMP := $(NPM_DIR)/node_modules/.installed
APT_PACKAGES := libusb-1.0-0 libgomp1 redis-server libllvm19 chromium
# Installed only when their command is missing (a NodeSource nodejs already brings npm).
APT_COMMANDS := node:nodejs npm:npm
DEMO_OUT ?= demo-out

.PHONY: setup system-packages demo test bench clean

setup: system-packages $(STAMP) $(NPM_STAMP)

# System packages (open3d needs libusb; the service tests need redis-server; the console's browser
# tests drive Debian's chromium; npm fetches the console's JavaScript: three.js, Swagger UI, ReDoc).
# Installed only when missing, with apt-get as root.
system-packages:
	@missing=""; for p in $(APT_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	for cp in $(APT_COMMANDS); do command -v $${cp%%:*} >/dev/null 2>&1 || missing="$$missing $${cp#*:}"; done; \
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

# The JavaScript the service serves (never from a CDN) and the glTF validator, pinned by package-lock.json.
$(NPM_STAMP): $(NPM_DIR)/package.json $(NPM_DIR)/package-lock.json
	cd $(NPM_DIR) && npm ci --no-audit --no-fund --ignore-scripts
	touch $(NPM_STAMP)

demo: setup
	$(PY) -m service.demo --out $(DEMO_OUT) $(DEMO_ARGS)

test: setup
	$(PY) -m pytest -q

bench: setup
	$(PY) bench/demosaic.py

clean:
	rm -rf $(VENV) $(DEMO_OUT) .pytest_cache $(NPM_DIR)/node_modules
