#!/bin/bash
# Builds the wheel folder that lets recipes/device/train.sh run on a lent GPU machine (Python 3.12,
# torch 2.11 preinstalled, no network). Run here, from anywhere, with network:
#   bash recipes/device/make_wheels.sh [DEST]      DEST default .whl (relative to the repo root)
# then run recipes/device/train.sh there (its header: the `run` call, speeds, moving a run back here).
# Idempotent: a wheel already in DEST is not fetched again. Repo + wheels must stay under 64 MiB.
set -euo pipefail
cd "$(dirname "$0")/../.."
DEST=${1:-.whl}; mkdir -p "$DEST"; TMP=$(mktemp -d); trap 'rm -rf "$TMP"' EXIT
EXCLUDE=$(git rev-parse --git-path info/exclude)  # .whl/ stays out of git (it travels by carry)
grep -qxF '/.whl/' "$EXCLUDE" 2>/dev/null || echo '/.whl/' >>"$EXCLUDE"
PLAT=""  # pip matches manylinux_2_N exactly: name each N these wheels use
for p in manylinux_2_28 manylinux_2_27 manylinux_2_24 manylinux_2_17 manylinux2014; do
  PLAT+=" --platform ${p}_x86_64"
done
# Drops members of a wheel under the given prefixes or ending in .png, and their RECORD lines.
trim() { python3 - "$@" <<'PY'
import sys, zipfile
src, dst, *prefixes = sys.argv[1:]
gone = lambda name: name.startswith(tuple(prefixes)) or name.endswith(".png")
with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as zout:
    for info in zin.infolist():
        if gone(info.filename):
            continue
        data = zin.read(info)
        if info.filename.endswith(".dist-info/RECORD"):  # pip checks nothing, but keep RECORD true
            data = b"".join(l for l in data.splitlines(True) if not gone(l.split(b",")[0].decode()))
        zout.writestr(info, data, zipfile.ZIP_DEFLATED, 9)
PY
}
for spec in mujoco==3.17.0 dm_control==1.0.50 torchrl==0.14.1 tensordict==0.14.3 dm_tree==0.1.10 \
    hydra_core==1.3.8 antlr4_python3_runtime==4.9.3 orjson==3.13.0 omegaconf==2.3.1 pytorch_kinematics==0.10.0 \
    arm_pytorch_utilities==0.5.0 importlib_metadata==10.2.0 dm_env==1.6 hoptorch==0.1.4 pyvers==0.2.3 \
    pytorch_seed==0.2.0 pytest==9.2.0 pluggy==1.7.0 iniconfig==2.3.1 packaging==26.4 pygments==2.21.0; do
  compgen -G "$DEST/${spec/==/-}-*.whl" >/dev/null && continue  # already there
  rm -rf "$TMP"/*
  if [[ $spec == antlr4* ]]; then  # sdist only: build its (pure python) wheel here
    python3 -m pip wheel -q --no-deps -w "$TMP" "$spec"
  else
    python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp $PLAT \
      -d "$TMP" "$spec"
  fi
  whl=$(ls "$TMP"/*.whl); out="$DEST/$(basename "$whl")"
  case $spec in  # the two big ones: viewer/studio and test/model assets the training never loads
    mujoco==*) trim "$whl" "$out" mujoco/experimental/ mujoco/_render_filament ;;
    dm_control==*) trim "$whl" "$out" dm_control/locomotion/soccer/ dm_control/locomotion/walkers/assets/ \
      dm_control/locomotion/arenas/assets/ dm_control/suite/dog_assets/ dm_control/mujoco/testing/assets/ \
      dm_control/blender/ dm_control/mjcf/test_assets/ ;;
    *) mv "$whl" "$out" ;;
  esac
  echo "$out $(du -k "$out" | cut -f1) KiB"
done
total=$(cat "$DEST"/*.whl | wc -c)
echo "total $(awk "BEGIN {printf \"%.1f MB\", $total / 1e6}") in $DEST (keep well under 35 MB)"
