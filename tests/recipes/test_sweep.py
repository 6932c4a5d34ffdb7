"""recipes/sweep.yaml: a sweep wandb accepts, whose every key exists in the training config."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch
import yaml
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from tensordict import TensorDict

from pnp.task.stage_graph import pnp_default_reward_config
from pnp.training.collect import episode_metrics
from pnp.training.config import register
from pnp.training.pipeline import phase_config

ROOT = Path(__file__).resolve().parents[2]
register()

SWEEP = ROOT / "recipes" / "sweep.yaml"
DISTRIBUTIONS = {"uniform", "log_uniform_values", "int_uniform", "q_uniform", "normal", "log_uniform", "categorical"}


@pytest.fixture(scope="module")
def sweep():
    return yaml.safe_load(SWEEP.read_text())


@pytest.fixture(scope="module")
def train_cfg():
    with initialize_config_dir(config_dir=str(ROOT / "recipes" / "config"), version_base="1.3"):
        return compose("train")


def test_sweep_structure(sweep):
    assert (ROOT / sweep["program"]).is_file()
    assert sweep["method"] in {"grid", "random", "bayes"}
    assert sweep["metric"]["goal"] in {"maximize", "minimize"}
    assert "${args_no_hyphens}" in sweep["command"], "hydra needs key=value, not --key=value"
    assert sweep["command"][:3] == ["${env}", "${interpreter}", "${program}"]
    for name, spec in sweep["parameters"].items():
        assert set(spec) & {"values", "value", "distribution", "min"}, name
        if "distribution" in spec:
            assert spec["distribution"] in DISTRIBUTIONS, name
            assert spec["min"] < spec["max"], name


def test_swept_keys_exist_in_train_config(sweep, train_cfg):
    for key, spec in sweep["parameters"].items():
        assert OmegaConf.select(train_cfg, key, default="<missing>") != "<missing>", f"{key} not in train.yaml"
        values = spec.get("values", [spec.get("value", spec.get("min"))])
        with initialize_config_dir(config_dir=str(ROOT / "recipes" / "config"), version_base="1.3"):
            compose("train", overrides=[f"{key}={values[0]}"])  # hydra accepts the override


def test_mu_min_range_is_valid(sweep):
    spec = sweep["parameters"]["curriculum.mu_min"]
    mu = pnp_default_reward_config()["mu"]
    assert 0 < spec["min"] and spec["max"] <= min(mu.values())


def test_metric_is_logged(sweep):
    n, t, a = 2, 3, 1
    agents = TensorDict({"episode_stage": torch.full((n, t, a, 1), -1), "reward": torch.zeros(n, t, a, 1),
                         "stage_one_hot": torch.zeros(n, t, a, 7)},
                        batch_size=(n, t, a))
    flags = {k: torch.zeros(n, t, 1, dtype=torch.bool) for k in ("done", "success")}
    batch = TensorDict({"next": TensorDict({**flags, "agents": agents}, batch_size=(n, t))}, batch_size=(n, t))
    assert sweep["metric"]["name"] in episode_metrics(batch)


def test_swept_values_reach_the_phase_the_sweep_runs(sweep, tmp_path):
    command = [c for c in sweep["command"] if not c.startswith("${")]
    overrides = [f"{key}={spec.get('values', [spec.get('value', spec.get('max'))])[-1]}"
                 for key, spec in sweep["parameters"].items()]
    with initialize_config_dir(config_dir=str(ROOT / "recipes" / "config"), version_base="1.3"):
        cfg = compose("train", overrides=[*command, *overrides, f"out_dir={tmp_path}"])
    assert len(cfg.pipeline) == 1 and cfg.phases[cfg.pipeline[0]].exit is None  # a fixed budget, no early exit
    phase = phase_config(cfg, 0, None)
    for override in overrides:
        key, value = override.split("=", 1)
        assert str(OmegaConf.select(phase, key)) == str(yaml.safe_load(value)), key
