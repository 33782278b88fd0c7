# osdar-ar: `make demo` runs the main job, `make test` the test suite.
# Both install everything they need first (system packages, a virtualenv in .venv).
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: setup demo test test-full lint bench clean reliability

setup: $(STAMP)

$(STAMP): pyproject.toml scripts/install_system_deps.sh
	bash scripts/install_system_deps.sh
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	touch $(STAMP)

demo: setup
	$(VENV)/bin/osdar-ar demo --workdir demo_out

test: setup
	$(PY) -m ruff check .
	$(PY) -m mypy
	$(PY) -m pytest -q

test-full: setup
	OSDAR_FULL=1 $(PY) -m pytest -q

# Every scenario of ../shared/design/RELIABILITY.md in its full form, printing its figures
# (needs Redis and PostgreSQL on loopback; redis_restart restarts the local Redis). Each
# runs beside a CPU hog, one busy process per core (scripts/reliability/common.py: loaded).
RELIABILITY := idempotency_burst authz_matrix limits hostile_uploads poison kill_workers \
	store_outage redis_restart db_restart schemathesis_run dashboard_fuzz load_poll

reliability: setup
	@fail=0; for s in $(RELIABILITY); do \
		timeout 1800 $(PY) -m scripts.reliability.$$s || fail=1; \
	done; exit $$fail

lint: setup
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .

clean:
	rm -rf demo_out .pytest_cache
