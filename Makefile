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
# make bench CASE=real (or CASE="real qa"): only those benchmark cases
CASE ?=
# make annotate: the frame shown first, the port, the file to write, who annotates
FRAME ?=
PORT ?=
CONTACT ?=
ANNOTATOR ?=
# Every user variable reaches the recipes verbatim, through the environment: `override X :=
# $(value X)` keeps make from expanding it, and the recipe lines only say "$$X" (quoted), so no
# value is ever read as make or shell syntax (`make sequence SEQ='x`touch y`'` runs nothing).
USER_VARS := RECIPE SEQ STAGE FORCE OUT SEED FRAMES SCENARIOS MARKERS STRIDE PRED GT EXECUTOR CLUSTER SCHEDULER WORKERS CASE \
  FRAME PORT CONTACT ANNOTATOR
$(foreach v,$(USER_VARS),$(eval override $(v) := $$(value $(v))))
export $(USER_VARS)
# bash arrays of the optional arguments, built from those variables (FORCE: words, no globbing)
ARGS = force=(); read -ra _w <<< "$$FORCE"; for _s in "$${_w[@]}"; do force+=(--force "$$_s"); done; \
  until=(); [ -z "$$STAGE" ] || until=(--until "$$STAGE"); \
  dask=(); [ -z "$$EXECUTOR" ] || dask+=(--executor "$$EXECUTOR"); \
  [ -z "$$CLUSTER" ] || dask+=(--cluster "$$CLUSTER"); \
  [ -z "$$SCHEDULER" ] || dask+=(--scheduler "$$SCHEDULER"); \
  [ -z "$$WORKERS" ] || dask+=(--workers "$$WORKERS"); \
  loo=(); [ -z "$$MARKERS" ] || loo+=(--set "marker_loo.markers=[$$MARKERS]"); \
  [ -z "$$STRIDE" ] || loo+=(--set "marker_loo.stride=$$STRIDE"); \
  studio=(); [ -z "$$FRAMES" ] || studio+=(--frames "$$FRAMES"); \
  [ -z "$$SCENARIOS" ] || studio+=(--scenarios "$$SCENARIOS");
export PYTHONPATH := $(CURDIR)
export ANNY_CACHE_DIR ?= $(CURDIR)/assets/cache/anny

.PHONY: cluster-script setup browser demo test test-fast sequence loo release evaluate status bench studio lint clean annotate

setup:
	@bash scripts/setup.sh

demo: setup
	@$(ARGS) $(PY) -m pipeline demo --recipe "$$RECIPE" "$${force[@]}"
	@# the session stages over every sequence: qa, the release, the QA index, the benchmark
	@$(ARGS) $(PY) -m pipeline release --recipe "$$RECIPE" "$${dask[@]}"
	@$(PY) -m evaluate.session --recipe "$$RECIPE"

sequence: setup
	@test -n "$$SEQ" || { echo "usage: make sequence SEQ=<subject>/<action> [RECIPE=...]"; exit 2; }
	@$(ARGS) $(PY) -m pipeline sequence "$$SEQ" --recipe "$$RECIPE" "$${until[@]}" "$${force[@]}"

loo: setup
	@test -n "$$SEQ" || { echo "usage: make loo SEQ=<group>/<action> [RECIPE=...] [MARKERS=RELB,RWRA] [STRIDE=2]"; exit 2; }
	@$(ARGS) $(PY) -m pipeline sequence "$$SEQ" --recipe "$$RECIPE" --until marker_loo "$${loo[@]}" "$${force[@]}"

release: setup
	@$(ARGS) $(PY) -m pipeline release --recipe "$$RECIPE" "$${until[@]}" "$${force[@]}" "$${dask[@]}"
	@$(PY) -m evaluate.session --recipe "$$RECIPE"

# the job script a SLURM/PBS cluster configuration submits (printed, not submitted)
cluster-script: setup
	@test -n "$$CLUSTER" || { echo "usage: make cluster-script CLUSTER=recipes/cluster/slurm.yaml"; exit 2; }
	@$(PY) -m pipeline cluster-script --cluster "$$CLUSTER"

# make evaluate RECIPE=...: the recipe's release scored against its ground truth (stages.evaluate.truth);
# make evaluate PRED=dir GT=dir: any two folders in the CHI3D layout
evaluate: setup
	@$(ARGS) if [ -n "$$PRED" ]; then $(PY) -m evaluate "$$PRED" "$$GT"; else \
	  $(PY) -m pipeline release --recipe "$$RECIPE" --until evaluate "$${force[@]}" && \
	  $(PY) -m evaluate.session --recipe "$$RECIPE"; fi

# the contact annotation page of one sequence on http://127.0.0.1:$PORT/ (annotate/server.py);
# it writes the recipe's contact file of the sequence unless CONTACT=<file> names another
annotate: setup
	@test -n "$$SEQ" || { echo "usage: make annotate SEQ=<group>/<action> [RECIPE=...] [FRAME=n] [PORT=8765] [CONTACT=file.json] [ANNOTATOR=name]"; exit 2; }
	@a=(); [ -z "$$FRAME" ] || a+=(--frame "$$FRAME"); [ -z "$$PORT" ] || a+=(--port "$$PORT"); \
	  [ -z "$$CONTACT" ] || a+=(--out "$$CONTACT"); [ -z "$$ANNOTATOR" ] || a+=(--annotator "$$ANNOTATOR"); \
	  $(PY) -m annotate --recipe "$$RECIPE" --seq "$$SEQ" "$${a[@]}"

status: setup
	@$(PY) -m pipeline status --recipe "$$RECIPE"

studio: setup
	@$(ARGS) $(PY) -m studio --out "$$OUT" --seed "$$SEED" "$${studio[@]}"

# setup plus Debian's chromium (headless; the HTML report tests render with it)
browser:
	@bash scripts/setup.sh --browser

test: browser
	@MOCAP_REQUIRE_BROWSER=1 $(PY) -m pytest -q tests

test-fast: setup
	@$(PY) -m pytest -q -m "not slow" tests

bench: setup
	@read -ra cases <<< "$$CASE"; $(PY) -m bench "$${cases[@]}"

lint: setup
	@$(PY) -m ruff check .

clean:
	rm -rf outputs/* bench/work
