# Two commands set everything up on a fresh machine: `make run` and `make test`.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
SERVICE_STAMP := $(VENV)/.installed-service
DEV_STAMP := $(VENV)/.installed-dev

.PHONY: install install-service run test lint bench clean

# `make run` installs the engine and the service only; `make test` adds the test tooling (a superset).
$(SERVICE_STAMP): pyproject.toml scripts/install.sh
	bash scripts/install.sh service $(PYTHON) $(VENV)
	touch $(SERVICE_STAMP)

$(DEV_STAMP): pyproject.toml scripts/install.sh
	bash scripts/install.sh dev $(PYTHON) $(VENV)
	touch $(DEV_STAMP) $(SERVICE_STAMP)

install: $(DEV_STAMP)

install-service: $(SERVICE_STAMP)

run: $(SERVICE_STAMP)
	$(VENV)/bin/voxnerf serve

test: $(DEV_STAMP)
	$(VENV)/bin/ruff check .
	$(PY) -m pytest -q -ra -n 3 --dist loadfile --no-loadscope-reorder --max-worker-restart 0

# Every benchmark whose table of record docs/benchmarks.md keeps, alone on the machine (about 2 hours on 2 cores): make bench OUT=DIR
bench: $(DEV_STAMP)
	bash benchmarks/run_all.sh $(or $(OUT),bench_out)

lint: $(DEV_STAMP)
	$(VENV)/bin/ruff check .

clean:
	rm -rf $(VENV) build *.egg-info
