# Two commands: `make run` and `make test`. Each creates .venv if it is missing and installs the
# project into it; re-running is quick because the install is stamped on pyproject.toml.
PYTHON ?= $(shell command -v python3.11 || command -v python3.12 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: run test lint venv clean browser

venv: $(STAMP)

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	@touch $(STAMP)

# The main job: the daemon against the simulated cell (hwsim serve as its child), API on loopback.
run: $(STAMP)
	$(BIN)/clothd run --sim --config config.yaml

lint: $(STAMP)
	$(BIN)/ruff check clothd hwsim tests
	$(BIN)/mypy

# The dashboard's tests drive Debian's Chromium (no browser download); CI runs as root and installs it.
browser:
	@command -v chromium >/dev/null || { \
	  if [ "$$(id -u)" = 0 ]; then apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q chromium; \
	  else echo "make test: the browser tests need Debian's chromium: sudo apt-get install chromium"; exit 1; fi; }

test: lint browser
	$(BIN)/pytest -q

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .mypy_cache .ruff_cache out
