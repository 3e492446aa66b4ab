# Two entry points on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo test install bench devdata clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $(STAMP)

install: $(STAMP)

test: $(STAMP)
	$(BIN)/python -m pytest -q

demo: $(STAMP)
	@echo "== rank every sample curve against a re-posed, resampled, reversed trefoil ==" >&2
	$(BIN)/nfdmatch rank sample_curves/queries/trefoil-posed.obj sample_curves/library --top 8

bench: $(STAMP)
	$(BIN)/python benchmarks/bench_distance.py

devdata: $(STAMP)
	$(BIN)/python benchmarks/eval_devdata.py

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
