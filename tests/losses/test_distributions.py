"""TanhNormalGripper: binary gripper samples, log-probs that add up, Bernoulli credit."""
from __future__ import annotations

import torch
from torch import distributions as D

from pnp.losses.distributions import TanhNormalGripper, bernoulli_kl

LOW = torch.tensor([-1.0] * 7 + [0.0])
HIGH = torch.tensor([2.0] * 7 + [1.0])


def _dist(n=64, seed=0):
    g = torch.Generator().manual_seed(seed)
    loc = torch.randn(n, 8, generator=g)
    scale = torch.rand(n, 8, generator=g) + 0.2
    return TanhNormalGripper(loc, scale, LOW, HIGH, gripper_index=7), loc, scale


def test_samples_are_binary_in_the_gripper_and_bounded_elsewhere():
    d, *_ = _dist()
    x = d.sample((10,))
    assert x.shape == (10, 64, 8)
    assert set(x[..., 7].unique().tolist()) <= {0.0, 1.0}
    assert (x[..., :7] > -1).all() and (x[..., :7] < 2).all()


def test_log_prob_is_tanh_normal_plus_bernoulli():
    d, loc, scale = _dist()
    x = d.sample()
    from torchrl.modules import TanhNormal
    arm = TanhNormal(loc[:, :7], scale[:, :7], low=LOW[:7], high=HIGH[:7]).log_prob(x[:, :7])
    grip = D.Bernoulli(logits=loc[:, 7]).log_prob(x[:, 7])
    torch.testing.assert_close(d.log_prob(x), arm + grip)


def test_gripper_log_prob_does_not_depend_on_its_scale():
    d, loc, scale = _dist()
    x = d.sample()
    scale2 = scale.clone()
    scale2[:, 7] *= 10
    torch.testing.assert_close(TanhNormalGripper(loc, scale2, LOW, HIGH, 7).log_prob(x), d.log_prob(x))


def test_deterministic_sample_closes_iff_p_above_half_and_kl_is_zero_to_itself():
    d, loc, _ = _dist()
    torch.testing.assert_close(d.deterministic_sample[:, 7], (loc[:, 7] > 0).float())
    assert d.kl_to(d).abs().max() < 1e-6
    shifted = TanhNormalGripper(loc + 0.5, torch.ones_like(loc), LOW, HIGH, 7)
    assert (d.kl_to(shifted) > 0).all()


def test_entropy_has_the_bernoulli_part_and_a_gradient():
    loc = torch.zeros(4, 8, requires_grad=True)
    d = TanhNormalGripper(loc, torch.ones(4, 8), LOW, HIGH, 7)
    e = d.entropy()
    assert e.shape == (4,) and torch.isfinite(e).all()
    e.sum().backward()
    assert loc.grad is not None


def test_bernoulli_kl_matches_torch_and_stays_finite_when_sharp():
    lp, lq = torch.tensor([-3.0, 0.5, 2.0]), torch.tensor([1.0, -0.5, 2.5])
    torch.testing.assert_close(bernoulli_kl(lp, lq), D.kl_divergence(D.Bernoulli(logits=lp), D.Bernoulli(logits=lq)))
    sharp_p, sharp_q = torch.tensor([15.0, -40.0, 25.0]), torch.tensor([20.0, -20.0, 20.0])
    assert torch.isinf(D.kl_divergence(D.Bernoulli(logits=sharp_p), D.Bernoulli(logits=sharp_q))).any()  # why
    kl = bernoulli_kl(sharp_p, sharp_q)
    assert torch.isfinite(kl).all() and (kl >= 0).all() and kl[2] > 0
    assert bernoulli_kl(sharp_p, sharp_p).abs().max() < 1e-6
