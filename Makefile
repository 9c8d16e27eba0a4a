# make demo  — set up .venv (if missing) and run the main job on the embedded data
# make test  — set up .venv (if missing) and run the test suite
# make bench — set up .venv and regenerate benchmarks/RESULTS.md and figures (20–60 min, by load)
# make bench-quick — the short suite (a few minutes), written to benchmarks/quick/

PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test bench bench-quick clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[test,bench]"
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/jaxnh demo

test: $(STAMP)
	$(PY) -m pytest tests

bench: $(STAMP)
	$(PY) -m benchmarks.run_all

bench-quick: $(STAMP)
	JAXNH_BENCH_OUT=benchmarks/quick $(PY) -m benchmarks.run_all --quick

clean:
	rm -rf $(VENV) jaxnh_out .pytest_cache benchmarks/quick
