# Two commands from a fresh clone: `make demo` (the main job) and `make test`.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin

.PHONY: demo test install bench clean browser notebooks

$(BIN)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e ".[test]"
	touch $@

install: $(BIN)/.installed

## the main job: the paper reproduced on the built-in simulated cohort, written to results/demo/
demo: $(BIN)/.installed
	$(BIN)/quadshank demo --out results/demo --overwrite

## the report test opens pages in a real headless browser: Debian's Chromium, installed once
CHROMIUM := /usr/bin/chromium
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
$(CHROMIUM):
	$(SUDO) apt-get update -qq
	$(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends chromium >/dev/null

browser: $(CHROMIUM)

## the test suite: two workers, each test file whole on one of them (module fixtures run once),
## in the order tests/conftest.py gives (the longest files first: --no-loadscope-reorder);
## XLA compiles on one thread, so two files compiling at once use both cores.
## A worker that crashes is not replaced: with --dist loadfile a replacement would rerun the
## crashing test, and its file's module fixtures, until the restart budget is spent.
test: $(BIN)/.installed $(CHROMIUM)
	$(BIN)/python -m pytest -q -n 2 --dist loadfile --no-loadscope-reorder --max-worker-restart=0 --durations=15

## the notebooks executed at full size from their sources (notebooks/*.py), written as .ipynb with outputs
notebooks: $(BIN)/.installed
	$(BIN)/python notebooks/execute.py

## benchmarks (results written to results/)
bench: $(BIN)/.installed
	$(BIN)/python benchmarks/bench_jphi.py

clean:
	rm -rf $(VENV) results/demo notebooks/_work
