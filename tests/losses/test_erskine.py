"""Erskine et al.'s loss: routing by stage, the mixed advantage by hand, per-stage GAE."""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from pnp.losses.erskine import CooperativeGAE, CooperativeMAPPOLoss, mixed_advantage
from pnp.baselines.per_stage import baseline_loss, use_baseline_schedule
from pnp.training.collect import collect
from pnp.training.keys import ADVANTAGE, LOC, OBS, SCALE, STAGE, STAGE_ONE_HOT, VALUE, VALUE_TARGET
from pnp.training.models import PopArt, make_models
from pnp.training.tasks import make_env
from pnp.training.trainer import make_loss
from tests.training._tiny import TINY, compose_cfg, tiny_train

ERSKINE = [*TINY, "model.per_stage=erskine", "curriculum.schedule=fixed"]


@pytest.fixture(scope="module")
def erskine():
    torch.manual_seed(0)
    cfg = compose_cfg("train", ERSKINE)
    env = make_env(cfg.env, cfg.curriculum, 0)
    use_baseline_schedule(env, cfg)
    return cfg, env, make_models(cfg.model, cfg.loss, env)


def test_mixed_advantage_on_a_hand_made_batch():
    per_stage = torch.tensor([[1.0, 2.0, 4.0]]).expand(3, 3).unsqueeze(1)  # [3 samples, 1 agent, K stages]
    stage = torch.tensor([0, 1, 2]).reshape(3, 1, 1)
    mixed = mixed_advantage(per_stage, stage, 0.25)
    # (1 - c) A_s + c A_{s+1}; the last stage keeps its own
    assert mixed.reshape(-1).tolist() == [0.75 * 1 + 0.25 * 2, 0.75 * 2 + 0.25 * 4, 4.0]
    assert mixed_advantage(per_stage, stage, 0.0).reshape(-1).tolist() == [1.0, 2.0, 4.0]
    with pytest.raises(ValueError, match=r"stage outside \[0, 2\]: \[3\]"):
        mixed_advantage(per_stage, torch.full((3, 1, 1), 3), 0.5)


def test_cooperative_gae_runs_one_gae_per_critic_then_mixes():
    """One world, 2 steps, 3 stages, lambda 0: A_i,t = r_i,t + gamma V_i(t+1) - V_i(t), cut at done."""
    value = torch.tensor([[1.0, 0.0, 2.0], [0.5, 1.0, 0.0]]).reshape(1, 2, 1, 3)
    next_value = torch.tensor([[0.5, 1.0, 0.0], [3.0, 3.0, 3.0]]).reshape(1, 2, 1, 3)
    reward = torch.tensor([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]]).reshape(1, 2, 1, 3)
    done = torch.tensor([False, True]).reshape(1, 2, 1)
    agents = TensorDict({"state_value": value, "stage": torch.tensor([0, 1]).reshape(1, 2, 1, 1)}, [1, 2, 1])
    nxt = TensorDict({"agents": TensorDict({"stage_rewards": reward, "state_value": next_value}, [1, 2, 1]),
                      "done": done, "terminated": done.clone()}, [1, 2])
    td = TensorDict({"agents": agents, "next": nxt}, [1, 2])
    gae = CooperativeGAE(mix=0.5, gamma=0.5, lmbda=0.0, value_network=None)
    gae.set_keys(value=("agents", "state_value"), reward=("agents", "stage_rewards"), advantage=ADVANTAGE,
                 value_target=VALUE_TARGET)
    gae(td)
    expected = torch.tensor([[1 + 0.5 * 0.5 - 1, 0 + 0.5 * 1 - 0, 0 + 0 - 2],  # t=0 bootstraps
                             [0 - 0.5, 2 - 1, 0 - 0]])  # t=1 terminated: no bootstrap
    torch.testing.assert_close(td["agents", "stage_advantage"].reshape(2, 3), expected)
    torch.testing.assert_close(td[VALUE_TARGET].reshape(2, 3), expected + value.reshape(2, 3))
    mixed = [0.5 * expected[0, 0] + 0.5 * expected[0, 1], 0.5 * expected[1, 1] + 0.5 * expected[1, 2]]
    torch.testing.assert_close(td[ADVANTAGE].reshape(2), torch.stack(mixed))
    with pytest.raises(ValueError, match="mix"):
        CooperativeGAE(mix=1.5, gamma=0.5, lmbda=0.0, value_network=None)


def test_each_sample_is_acted_by_its_stages_actor_and_valued_by_every_critic(erskine):
    _, env, models = erskine
    td = env.reset()[:1].expand(7).clone()  # one world per stage
    td[OBS] = torch.randn_like(td[OBS])
    td[STAGE_ONE_HOT] = torch.eye(7).reshape(7, 1, 7)
    actor, critic = models.actor_net, models.critic_net
    with torch.no_grad():
        out = models.actor(td.clone())
        values = models.critic(td.clone())[VALUE]
        x = models.obs_norm(td[OBS])
        for s in range(7):
            loc, scale = actor.head(actor.members[s](x[s:s + 1], td[STAGE_ONE_HOT][s:s + 1]))
            torch.testing.assert_close(out[LOC][s:s + 1], loc)
            torch.testing.assert_close(out[SCALE][s:s + 1], scale)
        own = torch.cat([m(x, td[STAGE_ONE_HOT]) for m in critic.members], -1)
        torch.testing.assert_close(values, critic.head(own))
    assert values.shape == (7, 1, 7)
    # a sample in S2 moves only the S2 actor
    actor.zero_grad(set_to_none=True)
    models.actor(td[2:3].clone())[LOC].sum().backward()
    grads = [any(p.grad is not None and p.grad.abs().sum() > 0 for p in m.parameters()) for m in actor.members]
    assert grads == [s == 2 for s in range(7)]
    actor.zero_grad(set_to_none=True)


def test_loss_trains_every_critic_on_its_own_target(erskine):
    cfg, env, models = erskine
    loss_cls, kwargs = baseline_loss(cfg)
    loss = make_loss(cfg.loss, models, loss_cls, **kwargs)
    assert isinstance(loss, CooperativeMAPPOLoss) and loss.mix == 0.5
    batch, _ = collect(env, models.actor, env.reset(), 5)
    with torch.no_grad():
        loss.value_estimator(batch)
    assert batch[VALUE_TARGET].shape == (4, 5, 1, 7) and batch[ADVANTAGE].shape == (4, 5, 1, 1)
    torch.testing.assert_close(batch[ADVANTAGE], mixed_advantage(batch["agents", "stage_advantage"], batch[STAGE], 0.5))
    loss.update_value_norm(batch)
    out = loss(batch.reshape(-1))
    for key in ("loss_objective", "loss_critic", "loss_entropy", "kl"):
        assert out[key].shape == (), key
    assert out["explained_variance"].shape[-1] == 7


def test_popart_of_several_values_preserves_each_output():
    torch.manual_seed(0)
    head, x = PopArt(beta=0.5, width=3), torch.randn(64, 3)
    head.update(torch.randn(64, 3))
    before = head(x)
    head.update(torch.randn(64, 3) * torch.tensor([1.0, 50.0, 0.1]) + torch.tensor([0.0, -200.0, 3.0]))
    torch.testing.assert_close(head(x), before, rtol=1e-4, atol=1e-3)


def test_erskine_trains_end_to_end(tmp_path):
    out = tiny_train(tmp_path / "run", "total_iterations=2", "model.per_stage=erskine", "curriculum.schedule=fixed")
    assert out["iteration"] == 2 and out["train/loss_critic"] > 0
    with pytest.raises(ValueError, match="curriculum.schedule=fixed .* got 'dynamic'"):
        tiny_train(tmp_path / "bad", "total_iterations=1", "model.per_stage=erskine")
