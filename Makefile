# Two entry points for a fresh machine: `make demo` and `make test` (see README).
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp
DEMO_OUT ?= demo-output
# what ruff checks (lint, test) and format-checks
PY_PATHS := pipeline flows tests benchmarks fixtures

# The report test renders the HTML report in Debian's headless chromium.
SUDO := $(shell [ "$$(id -u)" -eq 0 ] || echo sudo)

.PHONY: demo test lint format-check fixtures clean browser

# The install also writes the editable package's bytecode once: where
# PYTHONDONTWRITEBYTECODE is set, every command would otherwise compile the modules it
# imports (~0.4 s of an audit).
$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	$(BIN)/python -m compileall -q pipeline flows > /dev/null
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/aeromag demo --out $(DEMO_OUT)

browser:
	@command -v chromium >/dev/null || { $(SUDO) apt-get update -qq && \
	  DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq chromium >/dev/null; }

# ruff check and format check first: either fails CI before the (long) test run
test: $(STAMP) lint format-check browser
	$(BIN)/python -m pytest -n 2 --dist loadfile --durations=25

lint: $(STAMP)
	$(BIN)/ruff check $(PY_PATHS)

format-check: $(STAMP)
	$(BIN)/ruff format --check $(PY_PATHS)

fixtures: $(STAMP)
	$(BIN)/python fixtures/make_fixtures.py

clean:
	rm -rf $(DEMO_OUT) .pytest_cache
