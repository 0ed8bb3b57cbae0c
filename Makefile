# Two entry points for a fresh machine (see README): `make demo` and `make test`.
VENV ?= .venv
PY := $(VENV)/bin/python
export PYTHONUNBUFFERED := 1
export HF_HUB_OFFLINE := 1
export TRANSFORMERS_OFFLINE := 1

.PHONY: setup demo test lint typecheck unit bench clean

setup:
	@bash scripts/setup.sh

demo: setup
	$(PY) -m clients.demo $(DEMO_ARGS)

lint: setup
	$(VENV)/bin/ruff check protocol mapper clients tests benchmarks

typecheck: setup
	$(VENV)/bin/mypy

unit: setup
	$(PY) -m pytest $(PYTEST_ARGS)

test: lint typecheck unit

bench: setup
	$(PY) benchmarks/ingest_rate.py

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache
