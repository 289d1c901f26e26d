# Offline MoCap ground-truth pipeline. Every target runs `setup` first (fast when nothing changed).
SHELL := /bin/bash
PY := .venv/bin/python
RECIPE ?= recipes/demo.yaml
SEQ ?=
STAGE ?=
FORCE ?=
OUT ?= data/studio
SEED ?= 3
FRAMES ?=
SCENARIOS ?=
MARKERS ?=
STRIDE ?=
PRED ?=
GT ?=
# scale-out (make release): EXECUTOR=serial|dask, CLUSTER=recipes/cluster/slurm.yaml, SCHEDULER=tcp://host:8786, WORKERS=N
EXECUTOR ?=
CLUSTER ?=
SCHEDULER ?=
WORKERS ?=
DASK_ARGS = $(if $(EXECUTOR),--executor $(EXECUTOR),) $(if $(CLUSTER),--cluster $(CLUSTER),) $(if $(SCHEDULER),--scheduler $(SCHEDULER),) $(if $(WORKERS),--workers $(WORKERS),)
export PYTHONPATH := $(CURDIR)
export ANNY_CACHE_DIR ?= $(CURDIR)/assets/cache/anny

.PHONY: cluster-script setup browser demo test test-fast sequence loo release evaluate status bench studio lint clean

setup:
	@bash scripts/setup.sh

demo: setup
	@$(PY) -m pipeline demo --recipe $(RECIPE) $(foreach f,$(FORCE),--force $(f))
	@# the session stages over every sequence: qa, the release, the QA index, the benchmark
	@$(PY) -m pipeline release --recipe $(RECIPE) $(DASK_ARGS)
	@$(PY) -m evaluate.session --recipe $(RECIPE)

sequence: setup
	@test -n "$(SEQ)" || { echo "usage: make sequence SEQ=<subject>/<action> [RECIPE=...]"; exit 2; }
	@$(PY) -m pipeline sequence "$(SEQ)" --recipe $(RECIPE) $(if $(STAGE),--until $(STAGE),) $(foreach f,$(FORCE),--force $(f))

loo: setup
	@test -n "$(SEQ)" || { echo "usage: make loo SEQ=<group>/<action> [RECIPE=...] [MARKERS=RELB,RWRA] [STRIDE=2]"; exit 2; }
	@$(PY) -m pipeline sequence "$(SEQ)" --recipe $(RECIPE) --until marker_loo $(if $(MARKERS),--set "marker_loo.markers=[$(MARKERS)]",) $(if $(STRIDE),--set marker_loo.stride=$(STRIDE),) $(foreach f,$(FORCE),--force $(f))

release: setup
	@$(PY) -m pipeline release --recipe $(RECIPE) $(if $(STAGE),--until $(STAGE),) $(foreach f,$(FORCE),--force $(f)) $(DASK_ARGS)
	@$(PY) -m evaluate.session --recipe $(RECIPE)

# the job script a SLURM/PBS cluster configuration submits (printed, not submitted)
cluster-script: setup
	@test -n "$(CLUSTER)" || { echo "usage: make cluster-script CLUSTER=recipes/cluster/slurm.yaml"; exit 2; }
	@$(PY) -m pipeline cluster-script --cluster $(CLUSTER)

# make evaluate RECIPE=...: the recipe's release scored against its ground truth (stages.evaluate.truth);
# make evaluate PRED=dir GT=dir: any two folders in the CHI3D layout
evaluate: setup
	@if [ -n "$(PRED)" ]; then $(PY) -m evaluate "$(PRED)" "$(GT)"; else \
	  $(PY) -m pipeline release --recipe $(RECIPE) --until evaluate $(foreach f,$(FORCE),--force $(f)) && \
	  $(PY) -m evaluate.session --recipe $(RECIPE); fi

status: setup
	@$(PY) -m pipeline status --recipe $(RECIPE)

studio: setup
	@$(PY) -m studio --out $(OUT) --seed $(SEED) $(if $(FRAMES),--frames $(FRAMES),) $(if $(SCENARIOS),--scenarios $(SCENARIOS),)

# setup plus Debian's chromium (headless; the HTML report tests render with it)
browser:
	@bash scripts/setup.sh --browser

test: browser
	@MOCAP_REQUIRE_BROWSER=1 $(PY) -m pytest -q tests

test-fast: setup
	@$(PY) -m pytest -q -m "not slow" tests

bench: setup
	@$(PY) -m bench

lint: setup
	@$(PY) -m ruff check .

clean:
	rm -rf outputs/* bench/work
