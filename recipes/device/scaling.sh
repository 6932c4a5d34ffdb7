#!/bin/bash
# Device-side check of issue 66 on a lent GPU machine (16 cores): the device tests with their CUDA
# case, then recipes/analyze/scaling.py over 1, 4, 8, 16 threads on cpu and cuda (~5 min).
# Needs the wheels of recipes/device/make_wheels.sh in .whl/; `run` tool call:
#   command="PNP_COMMIT=<short hash sent> bash recipes/device/scaling.sh", carry=[".whl"], timeout_s=600
# The tracked tree must stay under 64 MiB with the wheels: untrack the checkpoints for the call.
# Back in files_at: scaling.json (-> results/scaling_h200.json) and tests.log.
set -uo pipefail
cd "$(dirname "$0")/../.."
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"
SETUP_ONLY=1 bash recipes/device/train.sh out_dir=runs/scaling || exit 1  # installs into $SITE, links pnp
export PYTHONPATH=${SITE:-/tmp/site}:$PWD MUJOCO_GL=disable PYTHONUNBUFFERED=1 PYTHONDONTWRITEBYTECODE=1
echo "== $(nproc) cores, $(nvidia-smi -L 2>/dev/null | head -1)"
# pnp imported from the link farm first (-P: not from the cwd), else pytest's rootdir insertion finds ./pnp (no losses/)
timeout 120 python3 -P -c "import sys, pnp, pytest; sys.exit(pytest.main(sys.argv[1:]))" -q -p no:cacheprovider \
  tests/training/test_device.py 2>&1 | tee "$OUT/tests.log"
[ -n "${TESTS_ONLY:-}" ] && exit 0
timeout 400 python3 recipes/analyze/scaling.py threads=1,4,8,16 devices=cpu,cuda iterations=2 \
  out="$OUT/scaling.json" 2>&1 | grep -v "it/s\]$"
