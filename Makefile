# The README's two set-up commands: `make train` (main job) and `make test`.
# Each creates and reuses .venv; torch is pinned here (a local CPU wheel on our machines).
PY := .venv/bin/python
STAMP := .venv/.installed

$(STAMP): pyproject.toml
	test -x $(PY) || python3 -m venv .venv
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e ".[sim,train,test,deploy,cluster]"
	touch $(STAMP)

.PHONY: venv test test-all train train-seeds benchmark render-deps
venv: $(STAMP)

test: $(STAMP)
	WANDB_MODE=offline MUJOCO_GL=egl $(PY) -m pytest -q

test-all: $(STAMP)
	WANDB_MODE=offline MUJOCO_GL=egl $(PY) -m pytest -q -m ""

# Main job: the single-robot pipeline from random weights (recipes/config/experiment/
# single_pnp_pipeline_bar.yaml over single_pnp_pipeline.yaml: kinematic phases, then MuJoCo),
# then a checkpoint chosen among the last phase's snapshots on the selection seeds 777 and
# 778, then 500 paired trials of it on the reporting seed (docs/guide/evaluation.md) into
# runs/main (results/ holds only quoted figures). Ctrl-C checkpoints; re-running resumes.
# SEED=k trains with seed k (else the schema's); the seeds of one commit: recipes/seed_study.py.
RUN ?= runs/main
train: $(STAMP)
	WANDB_MODE=offline $(PY) recipes/train.py experiment=single_pnp_pipeline_bar out_dir=$(RUN) $(if $(SEED),seed=$(SEED)) $(ARGS)
	$(PY) recipes/select_checkpoint.py run=$(RUN)
	$(PY) recipes/evaluate.py checkpoint=$(RUN) selected=true seed=reporting out=$(RUN)/eval_single_pnp.json

# make train over seeds, one after another (SEEDS="0 1 2"), each from its own empty folder
# runs/seed_<k>; a seed whose evaluation exists is skipped, so re-running resumes the study.
# Then the seeds gathered: mean, worst and spread (recipes/seed_study.py).
SEEDS ?= 0 1 2
comma := ,
empty :=
space := $(empty) $(empty)
train-seeds: $(STAMP)
	for k in $(SEEDS); do test -f runs/seed_$$k/eval_single_pnp.json || $(MAKE) train SEED=$$k RUN=runs/seed_$$k || exit 1; done
	$(PY) recipes/seed_study.py runs=[$(subst $(space),$(comma),$(addprefix runs/seed_,$(strip $(SEEDS))))]

benchmark: $(STAMP)
	$(PY) recipes/benchmark.py

# Offscreen rendering on CPU (Debian's Mesa EGL); the render test skips without it.
render-deps:
	apt-get update -q && apt-get install -y -q libegl1 libegl-mesa0 libgl1-mesa-dri
