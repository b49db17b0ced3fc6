# selfcal — everything a newcomer needs: `make demo` and `make test`.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: install demo test test-slow bench lint docs clean

# The stamp makes `make demo` / `make test` install nothing new once .venv exists
# and pyproject.toml is unchanged.
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/selfcal demo --out demo-output

test: $(STAMP)
	OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 $(PY) -m pytest -n 2 -q

test-slow: $(STAMP)
	OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 $(PY) -m pytest -n 2 -q -m "slow or not slow"

bench: $(STAMP)
	@# poselib is the baseline of bench_aoa only, never a dependency of the package
	$(PY) -m pip install --quiet 'poselib>=2.0' || echo 'poselib unavailable: bench_aoa skips its baseline'
	OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 $(PY) benchmarks/run_all.py --out benchmarks/results

# The documentation site (Sphinx + numpydoc + sphinx-click), warnings are errors; then the
# Examples sections of the public API's docstrings run as doctests.
docs: $(STAMP)
	$(VENV)/bin/sphinx-build -b html -W --keep-going -q docs docs/_build/html
	OPENBLAS_NUM_THREADS=1 $(PY) -m pytest -q -p no:cacheprovider tests/test_docs.py
	@echo "docs: open docs/_build/html/index.html"

lint: $(STAMP)
	$(VENV)/bin/ruff check src tests benchmarks
	$(VENV)/bin/mypy src

clean:
	rm -rf $(VENV) demo-output .pytest_cache .mypy_cache .ruff_cache docs/_build docs/_generated
