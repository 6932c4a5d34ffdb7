"""PopArtMAPPOLoss: its outputs, its KL, PopArt's output preservation, the adaptive lr rule."""
from __future__ import annotations

import pytest
import torch
from omegaconf import OmegaConf
from tensordict.nn import InteractionType, set_interaction_type

from pnp.losses.mappo import PopArtMAPPOLoss, policy_kl
from pnp.training.keys import LOC, SCALE, VALUE_TARGET
from pnp.training.models import PopArt, dist_from_params, make_models
from pnp.training.ppo import adapt_lr
from pnp.training.tasks import make_env
from pnp.training.trainer import make_loss
from tests.losses._batch import tiny_models_and_batch
from tests.training._tiny import TINY, compose_cfg


@pytest.fixture(scope="module")
def setup():
    cfg, models, batch = tiny_models_and_batch()
    loss = make_loss(cfg.loss, models)
    with torch.no_grad():
        loss.value_estimator(batch)
    return cfg, models, loss, batch.reshape(-1)


def test_forward_returns_the_loss_entries_and_a_zero_kl_before_any_step(setup):
    _, _, loss, batch = setup
    assert isinstance(loss, PopArtMAPPOLoss)
    out = loss(batch)
    for key in ("loss_objective", "loss_critic", "loss_entropy", "kl", "kl_approx", "clip_fraction", "entropy"):
        assert key in out.keys(), key
    for key in ("loss_objective", "loss_critic", "loss_entropy"):
        assert out[key].shape == () and out[key].requires_grad, key
    assert float(out["kl"]) == pytest.approx(0.0, abs=1e-6)  # the batch was collected by this very policy
    assert batch[LOC].shape[-1] == 8  # the behaviour's parameters are what the KL reads


def test_kl_grows_when_the_policy_moves_and_matches_the_gaussian_formula(setup):
    cfg, models, loss, batch = setup
    moved = batch.clone()
    moved[LOC] = moved[LOC] + 0.3  # as if collected by another policy
    kl = float(loss(moved)["kl"])
    assert kl > 0.01
    # Written out: same scales, means 0.3 apart, so each Gaussian entry adds 0.3^2 / (2 s^2);
    # the gripper (last entry) is a Bernoulli whose logit is its loc: p log(p/q) + (1-p) log((1-p)/(1-q)).
    gauss = (0.3**2 / (2 * batch[SCALE][..., :7].double() ** 2)).sum(-1)
    p, q = torch.sigmoid(moved[LOC][..., 7].double()), torch.sigmoid(batch[LOC][..., 7].double())
    bern = p * torch.log(p / q) + (1 - p) * torch.log((1 - p) / (1 - q))
    torch.testing.assert_close(torch.tensor(kl, dtype=torch.float64), (gauss + bern).mean(), rtol=1e-4, atol=1e-6)


def test_one_actor_forward_per_loss_call(setup):
    """The KL reads the distribution MAPPOLoss built, not a second forward of the actor."""
    _, models, loss, batch = setup
    calls = []
    handle = models.actor.module[0].register_forward_hook(lambda *_: calls.append(1))
    try:
        loss(batch)
    finally:
        handle.remove()
    assert len(calls) == 1


def test_tanh_normal_kl_is_the_pre_tanh_gaussians():
    cfg = compose_cfg("train", [*TINY, "model.grasp_dist=tanh_normal"])
    env = make_env(cfg.env, cfg.curriculum, 0)
    actor = make_models(cfg.model, cfg.loss, env).actor
    td = actor(env.reset())
    other = td.clone()
    other[LOC] = other[LOC] + 0.5
    a, b = dist_from_params(actor, td), dist_from_params(actor, other)
    s = td[SCALE]
    expected = (0.5**2 / (2 * s**2)).sum(-1)  # equal scales: only the mean term
    torch.testing.assert_close(policy_kl(a, b), expected)


def test_popart_update_preserves_the_critic_outputs():
    torch.manual_seed(0)
    head = PopArt(beta=0.5)
    x = torch.randn(64, 1)
    head.update(torch.randn(64) * 3 + 10)  # first statistics: nothing to preserve yet
    before = head(x)
    head.update(torch.randn(64) * 50 - 200)  # the curriculum moved the returns by orders of magnitude
    torch.testing.assert_close(head(x), before, rtol=1e-4, atol=1e-3)
    assert float(head.stats.scale()) > 10  # ... and the statistics did move


def test_the_loss_moves_popart_only_in_update_value_norm(setup):
    _, models, loss, batch = setup
    state = {k: v.clone() for k, v in models.popart.state_dict().items()}
    loss(batch)
    assert all(torch.equal(v, models.popart.state_dict()[k]) for k, v in state.items())
    loss.update_value_norm(batch)
    assert not torch.equal(state["stats.debiasing_term"], models.popart.stats.debiasing_term)
    assert VALUE_TARGET in batch.keys(True)


def test_adaptive_lr_rule():
    ocfg = OmegaConf.create({"lr_schedule": "adaptive", "desired_kl": 0.01, "min_lr": 1e-4, "max_lr": 1e-2})
    opt = torch.optim.SGD([torch.zeros(1, requires_grad=True)], lr=1e-3)
    lr = lambda: opt.param_groups[0]["lr"]  # noqa: E731
    adapt_lr(opt, 0.03, ocfg)  # above 2x the target: smaller steps
    assert lr() == pytest.approx(1e-3 / 1.5)
    adapt_lr(opt, 0.01, ocfg)  # within [0.5, 2] x target: unchanged
    assert lr() == pytest.approx(1e-3 / 1.5)
    adapt_lr(opt, 0.001, ocfg)  # below half: larger steps
    assert lr() == pytest.approx(1e-3)
    for _ in range(50):
        adapt_lr(opt, 1.0, ocfg)
    assert lr() == pytest.approx(1e-4)  # floored
    for _ in range(50):
        adapt_lr(opt, 0.0, ocfg)
    assert lr() == pytest.approx(1e-2)  # capped
    adapt_lr(opt, 1.0, OmegaConf.create({**ocfg, "lr_schedule": "fixed"}))
    assert lr() == pytest.approx(1e-2)
    with pytest.raises(ValueError, match="'cosine'"):
        adapt_lr(opt, 1.0, OmegaConf.create({**ocfg, "lr_schedule": "cosine"}))


def test_deterministic_bernoulli_gripper_has_zero_kl_to_itself(setup):
    _, models, _, batch = setup
    with set_interaction_type(InteractionType.DETERMINISTIC):
        d = dist_from_params(models.actor, batch)
    assert float(policy_kl(d, d).abs().max()) < 1e-6
