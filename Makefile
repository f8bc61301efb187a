# Two commands do all the set-up on a machine with only python3: `make demo` and `make test`.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
# numba compiles each kernel once and caches it next to the module (or, where that folder is
# read-only, under the user's cache folder): no NUMBA_CACHE_DIR here, so `make demo`, the
# console script, python -m and notebooks all share one cache

.PHONY: demo test docs bench lint clean clean-cache

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(VENV)/.installed: pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e .
	touch $@

$(VENV)/.installed-test: pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $(VENV)/.installed $@

demo: $(VENV)/.installed
	$(BIN)/scatmodes demo

test: $(VENV)/.installed-test
	$(BIN)/python -m pytest

$(VENV)/.installed-docs: pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e '.[docs]'
	touch $(VENV)/.installed $@

# the site in docs/_build/html: Sphinx with warnings as errors, offline; then checks of the
# built pages (every public name indexed, nothing remote, no console errors in Chromium)
docs: $(VENV)/.installed-docs
	$(BIN)/python -m sphinx -W --keep-going -q -b html docs docs/_build/html
	SCATMODES_DOCS_SITE=docs/_build/html $(BIN)/python -m pytest -q -p no:cacheprovider \
		tests/test_docs.py

# benchmark scripts (not timed tests): they need the peers in the [bench] extra
bench: $(VENV)/.installed-test
	$(BIN)/python -m pip install --quiet -e '.[test,bench]'
	$(BIN)/python tests/benchmarks/bench_basis.py
	$(BIN)/python tests/benchmarks/bench_eval.py
	$(BIN)/python tests/benchmarks/bench_project.py
	$(BIN)/python tests/benchmarks/bench_simulate.py
	$(BIN)/python tests/benchmarks/bench_compress.py
	$(BIN)/python tests/benchmarks/bench_distributed.py
	$(BIN)/python tests/benchmarks/bench_cli.py

lint: $(VENV)/.installed-test
	$(BIN)/ruff check basis project compress tests

# numba's caches: a cached kernel is checked against its own file only, not against the
# kernels it inlines from other files, so remove them after editing a shared kernel module
clean-cache:
	rm -rf .numba_cache
	find basis project compress -path '*/__pycache__/*' \( -name '*.nbi' -o -name '*.nbc' \) -delete

clean: clean-cache
	rm -rf $(VENV) .pytest_cache scatmodes-out docs/_build docs/api
