# Two entry points for a fresh machine (see README): `make demo` and `make test`.
VENV ?= .venv
PY := $(VENV)/bin/python
export PYTHONUNBUFFERED := 1
export HF_HUB_OFFLINE := 1
export TRANSFORMERS_OFFLINE := 1

.PHONY: setup demo test lint typecheck docs unit bench wheel platforms clean

setup:
	@bash scripts/setup.sh

demo: setup
	$(PY) -m clients.demo $(DEMO_ARGS)

lint: setup
	$(VENV)/bin/ruff check protocol mapper clients govnesf tests benchmarks examples setup.py

typecheck: setup
	$(VENV)/bin/mypy

unit: setup
	$(PY) -m pytest $(PYTEST_ARGS)

# the documentation site (mkdocs.yml), warnings as errors, into build/site; its hook
# scripts/gen_docs.py writes the reference pages generated from the code first
docs: setup
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict -d build/site

test: lint typecheck docs unit

bench: setup
	$(PY) benchmarks/speed/ingest_rate.py

# the installable wheel (core + extras, docs/getting-started/install.md) into dist/
wheel: setup
	$(VENV)/bin/pip wheel --no-deps --no-build-isolation --no-index -w dist .

# pip download of the core for aarch64 Linux and macOS arm64 (PLATFORM_ARGS=--dry-run: metadata only)
platforms: setup
	bash scripts/check_platforms.sh $(PLATFORM_ARGS)

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache build dist
