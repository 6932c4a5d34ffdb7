"""A transforms-only install: ``pnp.transforms`` needs torch, torchrl and tensordict alone.

torchrl 0.14 imports mujoco itself whenever it is installed (``find_spec("mujoco.mjx")``
in ``torchrl.envs.custom``), so the subprocess hides the sim and train packages the way a
base install lacks them: ``sys.modules[name] = None`` makes both ``import`` and
``find_spec`` see them as absent.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

try:
    import tomllib  # Python 3.11+
except ModuleNotFoundError:
    tomllib = None

PYPROJECT = Path(__file__).resolve().parents[2] / "pyproject.toml"
HIDDEN = ["mujoco", "dm_control", "hydra", "wandb", "matplotlib", "pytorch_kinematics", "imageio"]
BASE = {"torch", "torchrl", "tensordict", "numpy"}
EXTRA_ONLY = {"mujoco", "dm-control", "pytorch-kinematics", "imageio", "hydra-core", "wandb", "matplotlib", "tqdm"}

IMPORT_TRANSFORMS = f"""
import json, os, sys
for name in {HIDDEN!r}:
    sys.modules[name] = None
import pnp.transforms
loaded = [m for m, v in sys.modules.items() if v is not None and m.split(".")[0] in {HIDDEN!r}]
print(json.dumps({{"loaded": loaded, "MUJOCO_GL": os.environ.get("MUJOCO_GL")}}))
"""


def requirement_name(req: str) -> str:
    """``"mujoco>=3.17,<4"`` -> ``"mujoco"``."""
    for sep in "<>=!~[;( ":
        req = req.split(sep)[0]
    return req.strip().lower().replace("_", "-")


def test_import_transforms_loads_no_sim_or_train_package():
    env = {k: v for k, v in os.environ.items() if k != "MUJOCO_GL"}
    out = subprocess.run(
        [sys.executable, "-c", IMPORT_TRANSFORMS], env=env, capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr[-3000:]
    seen = json.loads(out.stdout.strip().splitlines()[-1])
    assert seen["loaded"] == []
    assert seen["MUJOCO_GL"] is None  # only the modules that load mujoco set it


@pytest.mark.skipif(tomllib is None, reason="tomllib needs Python 3.11")
def test_base_dependencies_are_the_transforms_only():
    project = tomllib.loads(PYPROJECT.read_text())["project"]
    base = {requirement_name(r) for r in project["dependencies"]}
    extras = {name: {requirement_name(r) for r in reqs} for name, reqs in project["optional-dependencies"].items()}
    assert base <= BASE and {"torch", "torchrl", "tensordict"} <= base, base
    assert not base & EXTRA_ONLY
    assert {"mujoco", "dm-control", "pytorch-kinematics"} <= extras["sim"]
    assert {"hydra-core", "wandb", "matplotlib", "tqdm"} <= extras["train"]
    assert {"pytest", "pytest-timeout", "hypothesis"} <= extras["test"]
