# Two commands from a fresh clone: `make demo` (the main job) and `make test`.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin

.PHONY: demo test install bench clean

$(BIN)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e ".[test]"
	touch $@

install: $(BIN)/.installed

## the main job: the paper reproduced on the built-in simulated cohort, written to results/demo/
demo: $(BIN)/.installed
	$(BIN)/quadshank demo --out results/demo

## the test suite: two workers, each test file whole on one of them (module fixtures run once);
## XLA compiles on one thread, so two files compiling at once use both cores
test: $(BIN)/.installed
	$(BIN)/python -m pytest -q -n 2 --dist loadfile

## benchmarks (results written to results/)
bench: $(BIN)/.installed
	$(BIN)/python benchmarks/bench_jphi.py

clean:
	rm -rf $(VENV) results/demo
