"""Actor and critic: std bounds, the Bernoulli gripper, the per-agent centralised critic,
folding constant inputs."""
from __future__ import annotations

import math

import pytest
import torch
from tensordict.nn import InteractionType, set_interaction_type

from pnp.training.keys import ACTION, LOC, SCALE
from pnp.training.models import GRASP_ENTRY, AgentNet, ObsNorm, fold_constant_inputs, make_models
from pnp.training.tasks import make_env
from tests.training._tiny import TINY, compose_cfg


def _actor_env(*extra):
    cfg = compose_cfg("train", [*TINY, *extra])
    env = make_env(cfg.env, cfg.curriculum, 0)
    return make_models(cfg.model, cfg.loss, env).actor, env


def test_min_scale_floors_every_entry():
    actor, env = _actor_env("model.min_scale=0.2", "model.init_scale=0.01")
    assert torch.all(actor(env.reset())[SCALE] == 0.2)


def test_std_ceiling_bounds_the_continuous_entries_only():
    actor, env = _actor_env("model.min_scale=0.3", "model.max_scale=1.0", "model.init_scale=5.0")
    scale = actor(env.reset())[SCALE]
    cont = [i for i in range(scale.shape[-1]) if i != GRASP_ENTRY]
    assert scale[..., cont].max() <= 1.0 and scale[..., cont].min() >= 0.3
    assert scale[..., GRASP_ENTRY].min() > 1.0  # init_scale 5: the grasp entry is not capped
    with pytest.raises(ValueError, match="max_scale=0.1"):
        _actor_env("model.min_scale=0.3", "model.max_scale=0.1")


def test_bernoulli_gripper_actions_are_binary_and_deterministic_mode_thresholds():
    actor, env = _actor_env()
    td = env.reset()
    with set_interaction_type(InteractionType.RANDOM):
        out = actor(td.clone())
    assert set(out[ACTION][..., GRASP_ENTRY].unique().tolist()) <= {0.0, 1.0}
    logit = out[LOC][..., GRASP_ENTRY]
    with set_interaction_type(InteractionType.DETERMINISTIC):
        det = actor(td.clone())[ACTION][..., GRASP_ENTRY]
    assert torch.equal(det, (logit > 0).float())


def test_grasp_min_prob_floors_the_gripper_probability_only_from_below():
    actor, env = _actor_env("model.grasp_min_prob=0.05")
    head = actor.module[0].module.head
    raw = torch.tensor([[-30.0, -3.0, 0.0, 3.0, 30.0]]).T.expand(-1, 2 * env.full_action_spec_unbatched[ACTION].shape[-1]).contiguous()
    loc, _ = head(raw)
    p = torch.sigmoid(loc[:, GRASP_ENTRY])
    assert p.min() >= 0.05 and p[0] < 0.051  # a collapsed logit sits at the floor
    assert p[-1] > 0.999 and torch.all(p[1:] > p[:-1])  # no ceiling, order kept
    assert torch.equal(loc[:, :GRASP_ENTRY], raw[:, :GRASP_ENTRY])  # other entries untouched
    with pytest.raises(ValueError, match="grasp_min_prob=0.05"):
        _actor_env("model.grasp_min_prob=0.05", "model.grasp_dist=tanh_normal")


def test_grasp_floor_penalty_pulls_a_collapsed_logit_back_to_the_floor():
    actor, env = _actor_env("model.grasp_min_prob=0.05", "model.grasp_floor_coeff=0.5")
    head = actor.module[0].module.head
    n = 2 * env.full_action_spec_unbatched[ACTION].shape[-1]
    raw = torch.tensor([[-30.0, 0.0]]).T.expand(-1, n).clone().requires_grad_(True)
    head(raw)
    lo = math.log(0.05 / 0.95)
    penalty = head.penalty()
    assert torch.isclose(penalty, torch.tensor(0.5 * (lo + 30.0) ** 2 / 2))  # only the logit below the floor
    penalty.backward()
    assert raw.grad[0, GRASP_ENTRY] < -1.0 and raw.grad[1, GRASP_ENTRY] == 0.0  # descent raises it
    with torch.no_grad():
        head(raw)
    assert head.penalty() is None  # rollouts leave nothing behind


def test_grasp_open_min_prob_caps_p_closed_only_in_the_release_stages():
    actor, env = _actor_env("model.grasp_min_prob=0.05", "model.grasp_floor_coeff=0.5", "model.grasp_open_min_prob=0.05")
    head = actor.module[0].module.head
    n = 2 * env.full_action_spec_unbatched[ACTION].shape[-1]
    raw = torch.full((4, n), 9.0, requires_grad=True)  # a held box's saturated logit
    stage = torch.nn.functional.one_hot(torch.tensor([3, 4, 5, 6]), 7).float()
    loc, _ = head(raw, stage)
    p = torch.sigmoid(loc[:, GRASP_ENTRY])
    assert torch.all(p[:2] > 0.9998) and torch.all(p[2:] <= 0.95)  # carried: uncapped; placed, released: capped
    hi = math.log(0.95 / 0.05)
    penalty = head.penalty()
    assert torch.isclose(penalty, torch.tensor(0.5 * 2 * (9.0 - hi) ** 2 / 4))  # only the capped stages
    penalty.backward()
    assert torch.all(raw.grad[2:, GRASP_ENTRY] > 0) and torch.all(raw.grad[:2, GRASP_ENTRY] == 0)
    # the actor passes each robot's stage through
    td = env.reset()
    td["agents", "stage_one_hot"] = torch.nn.functional.one_hot(torch.full(td["agents", "stage_one_hot"].shape[:-1], 5), 7).float()
    assert torch.all(torch.sigmoid(actor(td)[LOC][..., GRASP_ENTRY]) <= 0.95)
    for bad in (("model.grasp_open_min_prob=0.05",), ("model.grasp_min_prob=0.05", "model.grasp_open_min_prob=0.6"),
                ("model.grasp_min_prob=0.05", "model.grasp_open_min_prob=0.05", "model.grasp_open_stages=[7]")):
        with pytest.raises(ValueError, match="grasp_open"):
            _actor_env(*bad)


def test_centralised_critic_gives_each_agent_its_own_value():
    torch.manual_seed(0)
    net = AgentNet(5, 1, 2, True, [16])
    obs, stage = torch.randn(3, 2, 3), torch.randn(3, 2, 2)
    v = net(obs, stage)
    assert v.shape == (3, 2, 1) and not torch.allclose(v[:, 0], v[:, 1])
    torch.testing.assert_close(net(obs.flip(1), stage.flip(1)), v.flip(1))  # permuting robots permutes values
    moved = obs.clone()
    moved[:, 1] += 1.0  # robot 0's value depends on robot 1's inputs
    assert not torch.allclose(net(moved, stage)[:, 0], v[:, 0])


def test_fold_constant_inputs_keeps_outputs_and_blinds_the_nets():
    torch.manual_seed(0)
    n_obs = 5
    norm = ObsNorm(n_obs)
    data = torch.randn(256, n_obs)
    data[:, 2] = 0.5  # an entry that never moved
    norm.update(data)
    for centralised in (False, True):
        net = AgentNet(n_obs + 2, 3, 2, centralised, [8], obs_norm=norm)
        old = net(data[:4, None].expand(4, 2, n_obs), torch.zeros(4, 2, 2))
        state = {k: v.clone() for k, v in norm.state_dict().items()}
        assert fold_constant_inputs(norm, [net]) == [2]
        torch.testing.assert_close(net(data[:4, None].expand(4, 2, n_obs), torch.zeros(4, 2, 2)), old)
        moved = data[:4, None].expand(4, 2, n_obs).clone()
        moved[..., 2] = 3.0  # the entry moves: the folded nets do not see it
        torch.testing.assert_close(net(moved, torch.zeros(4, 2, 2)), old)
        norm.load_state_dict(state)


def test_obs_norm_matches_the_batch_statistics():
    torch.manual_seed(0)
    norm, x = ObsNorm(3), torch.randn(1000, 3) * torch.tensor([1.0, 5.0, 0.1]) + 2
    for chunk in x.split(128):
        norm.update(chunk)
    torch.testing.assert_close(norm.mean.float(), x.mean(0), rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(norm.var.float(), x.var(0, unbiased=False), rtol=1e-4, atol=1e-4)
