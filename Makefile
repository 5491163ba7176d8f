# The README's two commands: `make demo` and `make test`.
# Both build the environment from nothing: a venv in .venv with the CPU build of
# torch 2.13.0 installed *before* the project (a plain `torch` requirement would
# pull GBs of CUDA packages), then the project; `make test` adds the test and
# `distributed` (Ray) and `gsplat` (the real gsplat package for the drop-in's test) extras.
# Installing also compiles the codec's and the renderer's numba kernels (about a minute, once).

VENV   ?= .venv
PYTHON ?= python3
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp
TEST_STAMP := $(VENV)/.installed-test-stamp
DEMO_OUT ?= demo-output

.PHONY: demo test test-fast venv clean

venv: $(STAMP)

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet torch==2.13.0
	$(BIN)/pip install --quiet -e ".[dev]"
	$(BIN)/python -m gscodec_shac.kernels --compile  # numba kernels compiled once, into numba's cache
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/gscodec-shac demo $(DEMO_OUT)

# The tests also cover the Ray executor and the gsplat drop-in, so they install those extras.
$(TEST_STAMP): $(STAMP)
	$(BIN)/pip install --quiet -e ".[dev,distributed,gsplat]"
	touch $(TEST_STAMP)

# The full suite (CI). -rs lists why each skipped test was skipped.
test: $(TEST_STAMP)
	$(BIN)/python -m pytest -q -rs

# The quick tier: everything but the tests marked slow (tests/slow_tests.txt, applied in
# tests/conftest.py; regenerate the list with scripts/slow_tests.py from measured durations).
test-fast: $(TEST_STAMP)
	$(BIN)/python -m pytest -q -rs -m "not slow"

clean:
	rm -rf $(VENV) $(DEMO_OUT) .pytest_cache
