"""Fast learning test: MAPPO with the stage rewards learns S0 -> S1 in well under a minute.

Task: the kinematic backend, 3 s episodes, and layouts that keep the env's boxes (assets,
sizes, poses) but put the robot 0.85-1.15 m behind one handle, heading along the bar
(+-0.2 rad): a reaching task. With the env's own layouts (robot 1.2-10 m from the box) the
first S1 endings appear only after ~1M frames (measured), too slow for the default run.

Measured (deterministic policy, 256 episodes; 40 iterations of 7680 frames, ~35 s of
training each on 2 uncontended cores): mean end-of-episode stage with the stage rewards
0.85, 0.64, 0.96 (seeds 0, 1, 2), with them zeroed (R_fixed only) 0.0, 0.0, 0.0. The
threshold 0.25 (a quarter of the episodes end with the gripper aligned above its handle)
sits well below the first and far above the second.
"""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

import pnp.envs.pnp_env as pnp_env
from pnp.box import HANDLE_INSET
from pnp.layout import START_RANGE, sample_layout

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "recipes"))
import evaluate as evaluate_recipe  # noqa: E402
import train as train_recipe  # noqa: E402

THRESHOLD = 0.25
CONFIG_DIR = str(ROOT / "recipes" / "config")
TRAIN = [
    "env.backend=kinematic", "env.num_worlds=256", "env.max_episode_steps=30", "collect.frames_per_batch=7680",
    "collect.minibatch_size=1920", "collect.num_epochs=4", "model.actor_cells=[128,128]",
    "model.critic_cells=[128,128]", "model.init_scale=0.3", "optim.lr=1e-3", "optim.desired_kl=0.02",
    "total_iterations=40", "seed=0", "logger.backend=csv", "progress=false",
]


def reach_layout(rng, m, num_robots, assets, tries=16, start_range=START_RANGE):
    """The env's layout, with each robot moved behind the box's -x handle, facing along +y of the box."""
    lay = sample_layout(rng, m, num_robots, assets, tries, start_range=start_range)
    xy, yaw = lay.box_xy_yaw[:, :2], lay.box_xy_yaw[:, 2]
    box_x = torch.stack([torch.cos(yaw), torch.sin(yaw)], -1)
    box_y = torch.stack([-torch.sin(yaw), torch.cos(yaw)], -1)
    handle = xy - (lay.box_size[:, :1] / 2 - HANDLE_INSET) * box_x
    base = handle - (0.85 + 0.3 * torch.rand(m, 1, generator=rng)) * box_y
    heading = yaw + math.pi / 2 + 0.4 * (torch.rand(m, generator=rng) - 0.5)
    lay.base = torch.cat([base, heading[:, None]], -1)[:, None].expand(m, num_robots, 3).clone()
    return lay


@pytest.fixture
def reach_layouts(monkeypatch):
    monkeypatch.setattr(pnp_env, "sample_layout", reach_layout)


def _mean_end_stage(tmp_path: Path, stage_rewards: bool) -> float:
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("train", overrides=[*TRAIN, f"curriculum.stage_rewards={stage_rewards}", f"out_dir={tmp_path}"])
        eval_cfg = compose("evaluate", overrides=[
            f"checkpoint={tmp_path}", "trials=256", "env.num_worlds=256", "env.max_episode_steps=30", "seed=123",
            f"out={tmp_path / 'eval.json'}", "progress=false",
        ])
    train_recipe.train(cfg)
    evaluate_recipe.evaluate(eval_cfg)
    return json.loads((tmp_path / "eval.json").read_text())["mean_end_stage"]


@pytest.mark.timeout(900)  # a hang guard; ~80 s on 2 idle cores
def test_stage_rewards_teach_gripper_ready(tmp_path, reach_layouts):
    with_stage_rewards = _mean_end_stage(tmp_path / "stage_rewards", True)
    without = _mean_end_stage(tmp_path / "fixed_only", False)
    assert with_stage_rewards >= THRESHOLD > without, (with_stage_rewards, without)
