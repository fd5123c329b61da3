# Two commands: `make run` and `make test`. Each creates .venv if it is missing and installs exactly the
# locked dependency set (requirements.lock, hashes checked) into it; re-running is quick because the
# install is stamped on pyproject.toml and the lock. `make lock` re-resolves after pyproject.toml changes.
PYTHON ?= $(shell command -v python3.11 || command -v python3.12 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
LOCK := requirements.lock
UV_VERSION := $(shell sed -n 's/^uv==\([^ ]*\).*/\1/p' $(LOCK))
COMPILE = $(BIN)/uv pip compile --quiet pyproject.toml --extra dev --universal --generate-hashes \
	--python-version 3.11

# Python keeps the bytecode of what it imports (__pycache__/, git-ignored), as it does by default. A shell
# that sets PYTHONDONTWRITEBYTECODE has every process compile clothd, hwsim and their libraries again,
# 2-3 s each; the tests start hundreds (daemons, hwsim, the CLI, the compute process).
unexport PYTHONDONTWRITEBYTECODE

.PHONY: run test lint lock lock-check venv clean browser postgres firmware firmware-stm32

venv: $(STAMP)

# uv is bootstrapped from PyPI with pip, at the version the lock names; then the venv is made exactly the
# lock (uv is in it, so it stays), and clothd itself is installed editable on top, without dependencies.
$(STAMP): pyproject.toml $(LOCK)
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	@test -x $(BIN)/uv || $(BIN)/python -m pip install --quiet "uv==$(UV_VERSION)"
	$(BIN)/uv pip sync --quiet --python $(BIN)/python $(LOCK)
	$(BIN)/uv pip install --quiet --python $(BIN)/python --no-deps -e .
	@touch $(STAMP)

lock: $(STAMP)
	$(COMPILE) -o $(LOCK)

# Fails when pyproject.toml asks for something the lock does not hold (the lock's pins are kept as
# preferences, so a new release elsewhere does not count as out of date).
lock-check: $(STAMP)
	@cp $(LOCK) $(VENV)/lock-check.txt
	@$(COMPILE) -o $(VENV)/lock-check.txt
	@diff -q -I '^#' $(LOCK) $(VENV)/lock-check.txt >/dev/null || \
	  { echo "$(LOCK) is out of date with pyproject.toml: run make lock"; exit 1; }

# The main job: the daemon against the simulated cell (hwsim serve as its child), API on loopback;
# PORT=8081 serves the dashboard and the API on another port; OPCUA_PORT=4841 the OPC UA server.
run: $(STAMP)
	$(BIN)/clothd run --sim --config config.yaml $(if $(PORT),--port $(PORT)) $(if $(OPCUA_PORT),--opcua-endpoint opc.tcp://127.0.0.1:$(OPCUA_PORT)/clothd/)

lint: $(STAMP)
	$(BIN)/ruff check clothd hwsim tests
	$(BIN)/mypy

# The dashboard's tests drive Debian's Chromium (no browser download); CI runs as root and installs it.
browser:
	@command -v chromium >/dev/null || { \
	  if [ "$$(id -u)" = 0 ]; then apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q chromium; \
	  else echo "make browser: the browser tests need Debian's chromium: sudo apt-get install chromium"; exit 1; fi; }

# clothd tune's shared-study test starts its own server from Debian's PostgreSQL (initdb and pg_ctl, kept
# under /usr/lib/postgresql/VERSION/bin); CI runs as root and installs it.
postgres:
	@ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1 || command -v initdb >/dev/null || { \
	  if [ "$$(id -u)" = 0 ]; then apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q postgresql; \
	  else echo "make postgres: the shared-study test needs Debian's postgresql: sudo apt-get install postgresql"; exit 1; fi; }

# The reference stepper firmware (deploy/firmware/): its C unit tests, and the host build that
# tests/test_firmware_host.py drives over a pty. Debian's gcc; CI runs as root and installs it.
firmware:
	@command -v gcc >/dev/null || { \
	  if [ "$$(id -u)" = 0 ]; then apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q gcc make; \
	  else echo "make firmware: the firmware needs Debian's gcc: sudo apt-get install gcc"; exit 1; fi; }
	$(MAKE) -C deploy/firmware host check

# The same firmware for an STM32F405, booted in QEMU's netduinoplus2 by tests/test_firmware_qemu.py:
# Debian's gcc-arm-none-eabi (no libc linked) and qemu-system-arm, about a minute to install.
firmware-stm32:
	@command -v arm-none-eabi-gcc >/dev/null && command -v qemu-system-arm >/dev/null || { \
	  if [ "$$(id -u)" = 0 ]; then apt-get update -q && \
	    DEBIAN_FRONTEND=noninteractive apt-get install -y -q gcc-arm-none-eabi qemu-system-arm; \
	  else echo "make firmware-stm32: the STM32 build needs: sudo apt-get install gcc-arm-none-eabi qemu-system-arm"; exit 1; fi; }
	$(MAKE) -C deploy/firmware stm32

# The tests marked clock_free (nothing asserted of elapsed time, no deadline) run on every core, a module
# marked xdist_group on one worker; then the rest, whose real-time loops must not share the machine with
# another test, one at a time.
test: lock-check lint browser postgres firmware firmware-stm32
	$(BIN)/pytest -q -n auto --dist loadgroup -m clock_free
	$(BIN)/pytest -q -m "not clock_free"

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .mypy_cache .ruff_cache out
	$(MAKE) -C deploy/firmware clean
