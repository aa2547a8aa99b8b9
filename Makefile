# Two commands on a fresh machine with Python 3.11+ and make:
#   make demo   -> creates .venv, installs jaxlens, renders out/demo.png
#   make test   -> installs the test extras, runs the whole suite (notebooks included)
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin

.PHONY: demo test test-slow test-min chromium docs docs-serve install install-test lint bench clean

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

test: install-test chromium
	$(BIN)/python -m pytest -n 2 --dist loadfile --nbmake -m "not benchmark" tests notebooks

# A Chromium for the browser test (tests/test_browser.py): one on the PATH, else
# Playwright's own build (downloaded into ~/.cache/ms-playwright), else, only where this
# runs as root, Debian's package through apt-get (which may first update apt's lists).
# Each step says what it does. JAXLENS_NO_BROWSER=1 installs nothing and skips the test;
# where none can be installed the test is skipped and says why.
chromium: install-test
	@if [ -n "$$JAXLENS_NO_BROWSER" ]; then \
	  echo "JAXLENS_NO_BROWSER is set: no Chromium installed, the browser test is skipped"; \
	elif command -v chromium >/dev/null 2>&1; then :; \
	else \
	  echo "the browser test needs Chromium: installing Playwright's build (JAXLENS_NO_BROWSER=1 skips it)"; \
	  $(BIN)/python -m playwright install chromium >/dev/null 2>&1 || \
	  { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && \
	    echo "Playwright's build failed: installing Debian's chromium with apt-get (as root)" && \
	    { export DEBIAN_FRONTEND=noninteractive; apt-get install -y -q chromium || \
	      { apt-get update -q && apt-get install -y -q chromium; }; } >/dev/null 2>&1; } || \
	  echo "no Chromium could be installed: the browser test will be skipped"; \
	fi

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

# The documentation site (mkdocs-material, mkdocstrings), notebooks executed, into
# build/site; strict: a warning or a broken link fails the build.
docs: install-test
	NO_MKDOCS_2_WARNING=1 JAXLENS_DOCS_EXECUTE=true $(BIN)/python -m mkdocs build --strict

# The same site served at http://127.0.0.1:8000, rebuilt as files change.
docs-serve: install-test
	NO_MKDOCS_2_WARNING=1 $(BIN)/python -m mkdocs serve

lint: install-test
	$(BIN)/python -m pip install --quiet ruff
	$(BIN)/ruff check jaxlens tests benchmarks
	$(BIN)/ruff format --check jaxlens tests benchmarks

bench: install-test
	$(BIN)/python benchmarks/run_all.py

clean:
	rm -rf $(VENV) $(VENV_MIN) out build/site
