#!/bin/bash
# Device-side training driver: runs recipes/train.py on a lent GPU machine (16 cores, Python 3.12,
# torch preinstalled, no network) from the wheels that recipes/device/make_wheels.sh puts in .whl/.
# The run folder is the out_dir= (fresh run) or resume= (continued run) argument; `run` tool call:
#   command="bash recipes/device/train.sh resume=runs/<run> total_iterations=N env.nthread=16"
#   carry=[".whl", "runs/<run>"], timeout_s=600
# A fresh run (carry=[".whl"]) names out_dir=runs/<run> and the recipe, as the benchmark used it:
#   warm_start=results/train_single/checkpoint_mujoco.pt warm_start_curriculum=true env.backend=mujoco
#   env.num_worlds=1024 env.nthread=16 env.max_episode_steps=300 collect.frames_per_batch=16384
#   collect.minibatch_size=4096 loss.entropy_coeff=0.0 model.min_scale=0.05 logger.backend=csv progress=false
# Back in files_at: checkpoint.pt, metrics.jsonl (whole history), train.log; copy the first two
# into runs/<run>/ here. Measured (1024 worlds, 16384 frames per batch, env.nthread=16,
# OMP_NUM_THREADS=4): 2.5 s per iteration on the H100 machine's 16 cores vs 5.5 s on the 2-core
# dev machine (env.nthread=2, OMP 2). A resumed run takes env.nthread from the command line, so `resume=runs/X
# env.nthread=2` continues it on the dev machine (torch there is 2.11, here 2.13).
# Training gets SIGTERM after TRAIN_S seconds (default 540): train.py then stops with a checkpoint,
# inside the tool's 600 s limit. OMP_NUM_THREADS defaults to 4. SETUP_ONLY=1: install and link, no run.
set -uo pipefail
SITE=${SITE:-/tmp/site}; OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"
cd "$(dirname "$0")/../.."
od=""; rs=""; for a in "$@"; do case $a in out_dir=*) od=${a#*=};; resume=*) rs=${a#*=};; esac; done
run=${rs:-$od}; run=${run%/}; run=${run%/checkpoint.pt}  # resume= wins: train.py keeps the checkpoint's folder
if [[ -z $run || $run == true || $run == latest ]]; then
  echo "train.sh: name the run folder: out_dir=runs/X or resume=runs/X"; exit 2
fi
if [ ! -f "$SITE/.installed" ]; then  # once per machine
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$SITE" .whl/*.whl \
    && touch "$SITE/.installed" || exit 1
fi
export PYTHONPATH=$SITE:$PWD MUJOCO_GL=disable PYTHONUNBUFFERED=1 PYTHONDONTWRITEBYTECODE=1
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-4}
# pyproject maps pnp.envs/transforms/losses to the top-level folders: a link farm instead of an install
mkdir -p "$SITE/pnp" && ln -sfn "$PWD"/pnp/* "$SITE/pnp/" \
  && for d in envs transforms losses; do ln -sfn "$PWD/$d" "$SITE/pnp/$d"; done
[ -n "${SETUP_ONLY:-}" ] && { echo "setup done: run folder $run"; exit 0; }
echo "== $(nproc) cores, $(nvidia-smi -L 2>/dev/null | head -1), run folder $run"; t0=$(date +%s)
timeout -s TERM -k 30 "${TRAIN_S:-540}" python3 recipes/train.py "$@" hydra.run.dir=/tmp/hydra_x 2>&1 \
  | tee "$OUT/train.log"
echo "== rc=${PIPESTATUS[0]} wall $(( $(date +%s) - t0 ))s"
cp "$run/checkpoint.pt" "$run/metrics.jsonl" "$OUT/" && tail -n 2 "$run/metrics.jsonl" | cut -c1-300
