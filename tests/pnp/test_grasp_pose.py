"""env.grasp_pose: what Table II's gripper_grasp_pose pays, the EE's height over its handle
(default) or its distance to the handle bar."""
from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from omegaconf import OmegaConf
from omegaconf.errors import ValidationError

import pnp.task as T
from pnp.envs.pnp_env import PnPEnv
from pnp.task.terms import REWARD_TERMS
from pnp.training.config import CurriculumConfig, EnvConfig
from pnp.training.tasks import make_env

COL = REWARD_TERMS.index("gripper_grasp_pose")


def _grasp_pose_paid(offsets: torch.Tensor, grasp_pose: str) -> tuple[torch.Tensor, torch.Tensor]:
    """The term and the alignment with the EE moved to its handle's centre plus ``offsets``
    [N, 3] (world frame), on a kinematic env's first state."""
    env = PnPEnv(num_worlds=len(offsets), backend="kinematic", seed=0, nthread=1, grasp_pose=grasp_pose)
    try:
        env.reset()
        action = env._last_action.clone()
        s = env.backend.state(env._goal, env._init_goal_dist, action[..., 7])
        handle = T.geometry(s).handle  # [N, 1, 3], the handle each robot is given
        s = dataclasses.replace(s, ee_pos=handle + offsets[:, None])
        g = T.geometry(s)
        terms = T.reward_terms(s, g, action, action, T.stage_conditions(s, g), grasp_pose=grasp_pose)
        return terms[:, 0, COL], g.align[:, 0]
    finally:
        env.close()


def _across_the_bar(n: int, metres: float) -> torch.Tensor:
    """Horizontal offsets of ``metres`` perpendicular to each world's handle bar (box y axis)."""
    env = PnPEnv(num_worlds=n, backend="kinematic", seed=0, nthread=1)
    try:
        env.reset()
        s = env.backend.state(env._goal, env._init_goal_dist, env._last_action[..., 7])
        across = s.box_rot[:, :, 0].clone()  # box x axis: horizontal and perpendicular to the bar
        across[:, 2] = 0.0
        return metres * across / across.norm(dim=-1, keepdim=True)
    finally:
        env.close()


def test_height_pays_the_height_only_and_bar_pays_the_distance_across_the_bar():
    off = _across_the_bar(3, 0.05)
    height, align = _grasp_pose_paid(off, "height")
    bar, align_bar = _grasp_pose_paid(off, "bar")
    assert torch.equal(align, align_bar)
    # At the handle's height, 5 cm across the bar: height pays in full, bar exp(-0.5).
    assert torch.allclose(height, align, atol=1e-5)
    assert torch.allclose(bar, math.exp(-0.5) * align, atol=1e-4)
    # On the bar (its centre, 2 cm above it): the two kernels agree.
    up = torch.tensor([[0.0, 0.0, 0.02]]).expand(3, 3)
    assert torch.allclose(_grasp_pose_paid(up, "bar")[0], _grasp_pose_paid(up, "height")[0], atol=1e-5)


def test_an_unknown_kernel_is_refused_by_name():
    with pytest.raises(ValueError, match="'xy'"):
        PnPEnv(num_worlds=1, backend="kinematic", seed=0, nthread=1, grasp_pose="xy")


def test_the_config_schema_carries_it_and_other_tasks_refuse_it():
    cfg = OmegaConf.merge(OmegaConf.structured(EnvConfig),
                          {"backend": "kinematic", "num_worlds": 2, "grasp_pose": "bar"})
    env = make_env(cfg, OmegaConf.structured(CurriculumConfig), 0)
    assert env.base_env.grasp_pose == "bar"
    with pytest.raises(ValidationError, match="grasp_pose"):
        OmegaConf.merge(OmegaConf.structured(EnvConfig), {"grasp_pose": "xy"})
    cfg.task = "ee_tracking"
    with pytest.raises(ValueError, match="grasp_pose"):
        make_env(cfg, OmegaConf.structured(CurriculumConfig), 0)
