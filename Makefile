# Two commands do everything on a fresh machine:
#   make demo   set up, then run the main job on an embedded synthetic capture
#   make test   set up, lint (ruff + mypy), build the docs (mkdocs --strict), then run the whole test suite
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
# The built documentation site (mkdocs.yml, docs/); `make docs` writes it here.
DOCS_SITE ?= build/site

# torch: the CPU build, this version, from TORCH_INDEX when set (e.g. https://download.pytorch.org/whl/cpu);
# unset, pip's configured index is used (on machines with a local CPU build of torch).
TORCH_VERSION ?= 2.13.0
TORCH_INDEX ?=
TORCH_PIP := $(if $(TORCH_INDEX),--extra-index-url $(TORCH_INDEX))
FLOORS_VENV := .venv-floors
# Processes of `make test` (2 for the 2-core CI machine; more where cores and memory allow).
TEST_PROCESSES ?= 2

.PHONY: setup system-packages demo lint docs test test-floors lock bench clean

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

# torch (a range in pyproject) is installed first as the CPU build; the install is redone when
# pyproject changes.
$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q $(TORCH_PIP) 'torch==$(TORCH_VERSION)'
	$(PY) -m pip install -q $(TORCH_PIP) -e '.[full,service,dev,mitsuba,docs]'
	touch $(STAMP)

# The JavaScript the service serves (never from a CDN) and the glTF validator, pinned by package-lock.json.
$(NPM_STAMP): $(NPM_DIR)/package.json $(NPM_DIR)/package-lock.json
	cd $(NPM_DIR) && npm ci --no-audit --no-fund --ignore-scripts
	touch $(NPM_STAMP)

demo: setup
	$(PY) -m service.demo --out $(DEMO_OUT) $(DEMO_ARGS)

# ruff (rules and complexity limit in pyproject.toml) and mypy on the library and the service.
lint: setup
	$(PY) -m ruff check pmvir service tests bench docs tools conftest.py
	$(PY) -m mypy

# The documentation site, offline, with every warning an error (a broken link, a docstring the API
# reference cannot render, a page missing from the nav).
docs: setup
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict --quiet -d $(DOCS_SITE)

# The suite on TEST_PROCESSES processes (pytest-xdist; conftest.py keeps a test file, and a folder
# whose conftest makes session fixtures, in one process), each with one OpenMP thread (BLAS, torch,
# open3d, COLMAP), so that the processes do not contend for the cores.
test: setup lint docs
	OMP_NUM_THREADS=1 $(PY) -m pytest -q -n $(TEST_PROCESSES) --dist loadgroup

# The declared lower bounds are true: a fresh venv with every dependency at its floor release
# series (tools/requirements.py floors), then the fast tests. .ci/run runs it after `make test`
# (about 3 minutes). torch's floor needs the CPU wheel index (PyPI's torch 2.4 is the CUDA build):
#   make test-floors TORCH_INDEX=https://download.pytorch.org/whl/cpu
# Without TORCH_INDEX, torch stays at TORCH_VERSION (the CPU build this machine installs).
test-floors: system-packages
	rm -rf $(FLOORS_VENV) && $(PYTHON) -m venv $(FLOORS_VENV)
	$(FLOORS_VENV)/bin/python -m pip install -q --upgrade pip packaging
	$(FLOORS_VENV)/bin/python tools/requirements.py floors full service dev \
	  $(if $(TORCH_INDEX),,| sed 's/^torch==.*/torch==$(TORCH_VERSION)/') > $(FLOORS_VENV)/floors.txt
	$(FLOORS_VENV)/bin/python -m pip install -q $(TORCH_PIP) -r $(FLOORS_VENV)/floors.txt
	$(FLOORS_VENV)/bin/python -m pip install -q --no-deps -e .
	$(FLOORS_VENV)/bin/python -m pytest -q -m "not slow" tests/io tests/test_stage_cache.py tests/service/test_service_units.py tests/service/test_service_api.py tests/service/test_service_hostile.py tests/service/test_service_security.py

# docker/requirements.lock from the tested venv (make setup first).
lock: setup
	{ sed -n '1,3p' docker/requirements.lock; $(PY) tools/requirements.py lock full service; } > docker/requirements.lock.new
	mv docker/requirements.lock.new docker/requirements.lock

bench: setup
	$(PY) bench/demosaic.py

clean:
	rm -rf $(VENV) $(FLOORS_VENV) $(DEMO_OUT) $(DOCS_SITE) .pytest_cache .ruff_cache .mypy_cache $(NPM_DIR)/node_modules
