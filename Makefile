# Two entry points on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
# the compiled kernels: rebuilt when their source changes (an edited _kernels.py is never
# served by a stale ahead-of-time build, but it would fall back to the slower paths)
KERNELS := $(VENV)/.kernels

.PHONY: demo test test-fast lint install bench devdata clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(STAMP): $(BIN)/python pyproject.toml setup.py
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $(STAMP)

$(KERNELS): $(STAMP) nfdmatch/matching/_kernels.py nfdmatch/matching/_graph_kernels.py nfdmatch/matching/_push_rounds.py nfdmatch/matching/_elastic_kernels.py nfdmatch/matching/common.py nfdmatch/matching/aot.py
	@echo "compiling the numba kernels once, also ahead of time (so that no query compiles or imports numba)" >&2
	@# what will serve, said: a kernel that fails to compile falls back (slower) without failing the install
	$(BIN)/python -c "from nfdmatch.matching import compile_kernels; from nfdmatch.matching.kernels import choose; \
		compile_kernels(); print('kernels that will serve:', choose().describe())" >&2
	touch $(KERNELS)

# the manual page, made from the commands' own help (`man ./nfdmatch.1` in the checkout;
# tests/test_never_destroy.py checks that the committed page is the one the help gives)
MAN := $(VENV)/share/man/man1/nfdmatch.1

nfdmatch.1: $(STAMP) $(wildcard nfdmatch/cli/*.py)
	$(BIN)/nfdmatch help --man > $@.tmp && mv $@.tmp $@

$(MAN): nfdmatch.1
	mkdir -p $(dir $@) && cp nfdmatch.1 $@

# bytecode too: a CLI start-up without it compiles every module from source (~60 ms more
# in an environment that sets PYTHONDONTWRITEBYTECODE, e.g. many containers)
install: $(STAMP) $(KERNELS) $(MAN)
	@$(BIN)/python -m compileall -q nfdmatch

test: install
	$(BIN)/python -m pytest -q

# the unit tests only (no end-to-end runs marked slow): under a minute
test-fast: install
	$(BIN)/python -m pytest -q -m "not slow"

lint: $(STAMP)
	$(BIN)/python -m ruff check nfdmatch tests benchmarks
	$(BIN)/python -m ruff format --check nfdmatch tests benchmarks

demo: install
	@echo "== index the sample curves (incremental: a second run recomputes nothing) ==" >&2
	@mkdir -p demo-out
	$(BIN)/nfdmatch index build sample_curves/library --index demo-out/demo.h5
	@echo "== query with a re-posed, resampled, reversed trefoil ==" >&2
	$(BIN)/nfdmatch query sample_curves/queries/trefoil-posed.obj --index demo-out/demo.h5 --top 8 --format table
	@echo "== see the best five, each aligned onto the query ==" >&2
	$(BIN)/nfdmatch show sample_curves/queries/trefoil-posed.obj --index demo-out/demo.h5 --top 5 -o demo-out/matches.png --format table
	@echo "== open demo-out/matches.png (the README shows the same picture: docs/images/demo-matches.png) ==" >&2

bench: install
	$(BIN)/python benchmarks/bench_distance.py
	$(BIN)/python benchmarks/bench_index.py
	$(BIN)/python benchmarks/bench_search.py
	$(BIN)/python benchmarks/bench_render.py

devdata: install
	$(BIN)/python benchmarks/eval_devdata.py

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache demo-out
