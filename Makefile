# Two commands on a fresh machine with Python 3.11+ and make:
#   make demo   -> creates .venv, installs jaxlens, renders out/demo.png
#   make test   -> installs the test extras, runs the whole suite (notebooks included)
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin

.PHONY: demo test test-slow test-min install install-test lint bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(VENV)/.installed: pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e .
	touch $@

$(VENV)/.installed-test: pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e '.[test,bench]'
	touch $(VENV)/.installed $@

install: $(VENV)/.installed

install-test: $(VENV)/.installed-test

demo: install
	mkdir -p out
	$(BIN)/jaxlens render -o out/demo.png

test: install-test
	$(BIN)/python -m pytest -n 2 --dist loadfile --nbmake -m "not benchmark" tests notebooks

# The tests marked `benchmark` (each ~40 s or more; their cases are also benchmarked).
test-slow: install-test
	$(BIN)/python -m pytest -n 2 --dist loadfile -m benchmark tests

# The core tests (not the notebooks) against the lowest declared dependency versions,
# in a separate environment: .ci/min-versions.txt pins them.
VENV_MIN := .venv-min
test-min:
	$(PYTHON) -m venv $(VENV_MIN)
	$(VENV_MIN)/bin/python -m pip install --quiet --upgrade pip
	$(VENV_MIN)/bin/python -m pip install --quiet -c .ci/min-versions.txt -e '.[test]'
	$(VENV_MIN)/bin/python -m pytest -n 2 --dist loadfile -m "not benchmark" tests

lint: install-test
	$(BIN)/ruff check jaxlens tests benchmarks
	$(BIN)/ruff format --check jaxlens tests benchmarks

bench: install-test
	$(BIN)/python benchmarks/run_all.py

clean:
	rm -rf $(VENV) $(VENV_MIN) out
