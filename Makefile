# make demo       — set up .venv (if missing) and run the main job on the embedded default data
# make test       — set up .venv (if missing) and run the test suite as CI does (every test not marked extended)
# make test-quick — the quick tier: every test not marked slow (nor extended)
# make test-all   — every test, the extended tier included
# make test-min   — a separate .venv-min with the oldest declared dependency versions; runs the quick tier
# make docs       — build the documentation site into site/ (examples executed; strict: warnings fail)
#                   warm builds reuse executed examples from .cache/docs-exec; JAXNH_DOCS_CACHE=off to re-run all
# make docs-serve — the same, served with live reload at http://127.0.0.1:8000
# make lint       — ruff check, ruff format --check, pyright
# make bench      — run the benchmark suite, regenerate benchmarks/RESULTS.md and figures (25–45 min on 2 cores)
# make bench-quick — the short suite (about 10 minutes), written to benchmarks/quick/
# make bench-stale — fail when benchmarks/RESULTS.md was measured on other jaxnh/ sources than today's

PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
MIN_VENV := .venv-min

.PHONY: demo test test-quick test-all test-min docs docs-serve lint bench bench-quick bench-stale clean

$(VENV)/.created:
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	touch $@

$(STAMP): pyproject.toml $(VENV)/.created
	$(PY) -m pip install --quiet -e ".[test,plot]"
	touch $@

$(VENV)/.installed-%: pyproject.toml $(STAMP)
	$(PY) -m pip install --quiet -e ".[$*]"
	touch $@

demo: $(STAMP)
	$(VENV)/bin/jaxnh demo

test: $(STAMP)
	$(PY) -m pytest tests -m "not extended"

test-all: $(STAMP)
	$(PY) -m pytest tests

test-quick: $(STAMP)
	$(PY) -m pytest tests -m "not slow"

test-min:
	test -x $(MIN_VENV)/bin/python || $(PYTHON) -m venv $(MIN_VENV)
	$(MIN_VENV)/bin/python -m pip install --quiet --upgrade pip
	$(PYTHON) .ci/min_pins.py > $(MIN_VENV)/pins.txt
	$(MIN_VENV)/bin/python -m pip install --quiet -r $(MIN_VENV)/pins.txt
	$(MIN_VENV)/bin/python -m pip install --quiet -c $(MIN_VENV)/pins.txt -e ".[test]"
	$(MIN_VENV)/bin/python -m pip list --format=freeze | grep -iE '^(jax|jaxlib|diffrax|equinox|optax|optimistix|jaxtyping|numpy|scipy|matplotlib)=='
	$(MIN_VENV)/bin/python -m pytest tests -m "not slow"

docs: $(VENV)/.installed-docs
	$(VENV)/bin/mkdocs build --strict

docs-serve: $(VENV)/.installed-docs
	$(VENV)/bin/mkdocs serve

lint: $(VENV)/.installed-dev
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/pyright

bench: $(VENV)/.installed-bench
	$(PY) -m benchmarks.run_all

bench-quick: $(VENV)/.installed-bench
	JAXNH_BENCH_OUT=benchmarks/quick $(PY) -m benchmarks.run_all --quick

bench-stale: $(STAMP)
	$(PY) -m benchmarks.run_all --stale

clean:
	rm -rf $(VENV) $(MIN_VENV) site jaxnh_out .pytest_cache benchmarks/quick
