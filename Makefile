# The README's two set-up commands: `make train` (main job) and `make test`.
# Each creates and reuses .venv; torch is pinned here (a local CPU wheel on our machines).
PY := .venv/bin/python
STAMP := .venv/.installed

$(STAMP): pyproject.toml
	test -x $(PY) || python3 -m venv .venv
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e ".[test]"
	touch $(STAMP)

.PHONY: venv test test-all train benchmark render-deps
venv: $(STAMP)

test: $(STAMP)
	WANDB_MODE=offline MUJOCO_GL=egl $(PY) -m pytest -q

test-all: $(STAMP)
	WANDB_MODE=offline MUJOCO_GL=egl $(PY) -m pytest -q -m ""

train: $(STAMP)
	WANDB_MODE=offline $(PY) recipes/train.py
	$(PY) recipes/evaluate.py

benchmark: $(STAMP)
	$(PY) recipes/benchmark.py

# Offscreen rendering on CPU (Debian's Mesa EGL); the render test skips without it.
render-deps:
	apt-get update -q && apt-get install -y -q libegl1 libegl-mesa0 libgl1-mesa-dri
