"""Warm starts across set-ups (recipes/_warm_start.py) and the per-agent centralised critic."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

from tests.recipes.test_train import _cfg, _train

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "recipes"))
import _common  # noqa: E402
from _warm_start import adapt_curriculum, load_module  # noqa: E402


def test_centralised_critic_gives_each_agent_its_own_value():
    torch.manual_seed(0)
    net = _common.AgentNet(5, 1, 2, True, [16])
    obs, stage = torch.randn(3, 2, 3), torch.randn(3, 2, 2)
    v = net(obs, stage)
    assert v.shape == (3, 2, 1) and not torch.allclose(v[:, 0], v[:, 1])
    swapped = net(obs.flip(1), stage.flip(1))  # permuting the robots permutes their values
    torch.testing.assert_close(swapped, v.flip(1))
    moved = obs.clone()
    moved[:, 1] += 1.0  # robot 0's value depends on robot 1's inputs
    assert not torch.allclose(net(moved, stage)[:, 0], v[:, 0])


def test_single_robot_checkpoint_warm_starts_the_dual_task(tmp_path):
    _train(tmp_path / "one", "total_iterations=2")
    _train(tmp_path / "two", "total_iterations=0", "env.num_robots=2", f"warm_start={tmp_path / 'one'}",
           "warm_start_curriculum=true", "env.num_worlds=3")
    a = _common.load_checkpoint(tmp_path / "one" / "checkpoint.pt")
    b = _common.load_checkpoint(tmp_path / "two" / "checkpoint.pt")
    for k in a["actor"]:
        assert torch.equal(a["actor"][k], b["actor"][k]), k
    w1, w2 = a["critic"]["module.mlp.params.0.weight"], b["critic"]["module.mlp.params.0.weight"]
    assert w2.shape[-1] == 2 * w1.shape[-1]
    assert torch.equal(w2[..., : w1.shape[-1]], w1) and not w2[..., w1.shape[-1]:].any()
    rho1, rho2 = a["curriculum"]["transforms.2.rho"], b["curriculum"]["transforms.2.rho"]
    assert rho2.shape == (3, 2, rho1.shape[-1]) and torch.equal(rho2[:, 1], rho1[:3, 0])

    # the widened critic values each robot as the single-robot critic valued it alone
    cfg1 = _cfg("train", ["env.backend=kinematic", "env.num_worlds=4", "model.critic_cells=[32,32]",
                          "model.actor_cells=[32,32]"])
    cfg2 = _cfg("train", ["env.backend=kinematic", "env.num_worlds=4", "env.num_robots=2",
                          "model.critic_cells=[32,32]", "model.actor_cells=[32,32]"])
    nets = []
    for cfg, state in ((cfg1, a["critic"]), (cfg2, b["critic"])):
        env = _common.make_env(cfg.env, cfg.curriculum, 0)
        _, critic, *_ = _common.make_models(cfg.model, env, "popart", 0.98)
        critic.load_state_dict(state)
        nets.append(critic.module)
    obs, stage = torch.randn(4, 2, 74), torch.eye(7)[torch.randint(0, 7, (4, 2))]
    alone = nets[0](obs.reshape(8, 1, 74), stage.reshape(8, 1, 7)).reshape(4, 2, 1)
    torch.testing.assert_close(nets[1](obs, stage), alone)


def test_widening_anything_but_the_first_layer_is_refused():
    net = _common.AgentNet(5, 1, 1, False, [8])
    state = _common.AgentNet(5, 1, 1, False, [16]).state_dict()
    with pytest.raises(ValueError, match="only the critic's first layer may widen"):
        load_module(net, state)


def test_adapt_curriculum_reuses_worlds_cyclically():
    state = {"rho": torch.arange(6.0).reshape(3, 1, 2), "hist": torch.arange(7)}
    out = adapt_curriculum(state, 5, 1)
    assert out["rho"][:, 0, 0].tolist() == [0, 2, 4, 0, 2] and torch.equal(out["hist"], state["hist"])
    with pytest.raises(ValueError, match="2 robots"):
        adapt_curriculum({"rho": torch.zeros(3, 2, 2)}, 3, 1)


def test_env_boxes_picks_the_assets():
    from pnp.box import DUAL_ROBOT_BOXES

    cfg = _cfg("train", ["env.backend=kinematic", "env.num_worlds=2", "env.boxes=dual"])
    assert _common.make_env(cfg.env, cfg.curriculum, 0).base_env.box_assets == DUAL_ROBOT_BOXES
    with pytest.raises(ValueError, match="'huge'"):
        bad = _cfg("train", ["env.backend=kinematic", "env.boxes=huge"])
        _common.make_env(bad.env, bad.curriculum, 0)


def test_env_box_blocks_base_reaches_the_kinematic_backend_only():
    cfg = _cfg("train", ["env.backend=kinematic", "env.num_worlds=2", "env.box_blocks_base=true"])
    assert _common.make_env(cfg.env, cfg.curriculum, 0).base_env.backend.params.box_blocks_base
    cfg = _cfg("train", ["env.backend=kinematic", "env.num_worlds=2"])
    assert not _common.make_env(cfg.env, cfg.curriculum, 0).base_env.backend.params.box_blocks_base


def test_std_ceiling_bounds_the_continuous_entries_only():
    cfg = _cfg("train", ["env.backend=kinematic", "env.num_worlds=4", "model.actor_cells=[16]", "model.critic_cells=[16]",
                         "model.min_scale=0.3", "model.max_scale=1.0", "model.init_scale=5.0"])
    env = _common.make_env(cfg.env, cfg.curriculum, 0)
    actor, *_ = _common.make_models(cfg.model, env, "popart", 0.98)
    td = actor(env.reset())
    scale = td["agents", "scale"]
    cont = [i for i in range(scale.shape[-1]) if i != _common.GRASP_ENTRY]
    assert scale[..., cont].max() <= 1.0 and scale[..., cont].min() >= 0.3
    assert scale[..., _common.GRASP_ENTRY].min() > 1.0  # init_scale 5: the grasp entry is not capped
    bad = _cfg("train", ["env.backend=kinematic", "env.num_worlds=4", "model.min_scale=0.3", "model.max_scale=0.1"])
    with pytest.raises(ValueError, match="max_scale=0.1"):
        _common.make_models(bad.model, env, "popart", 0.98)
