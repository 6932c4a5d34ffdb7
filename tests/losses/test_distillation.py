"""DistillationPPOLoss: hand-computed KLs for both parts of the action distribution, beta = 0
is the MAPPO loss, and the KL term pulls the student towards the teacher."""
from __future__ import annotations

import pytest
import torch

from pnp.losses.distillation import DistillationPPOLoss
from pnp.losses.mappo import PopArtMAPPOLoss
from pnp.training.keys import ACTION, ADVANTAGE, LOC, LOG_PROB, REWARD, SCALE, VALUE, VALUE_TARGET
from pnp.training.models import GRASP_ENTRY
from tests.losses._batch import tiny_models_and_batch

TEACHER_LOC, TEACHER_SCALE = ("agents", "teacher_loc"), ("agents", "teacher_scale")
SHIFT, SCALE_RATIO = 0.3, 1.5  # the teacher's loc = student's + SHIFT, its scale = student's x SCALE_RATIO


def _loss(cls, models, **kw):
    loss = cls(models.actor, models.critic, models.popart, entropy_coeff=0.01, **kw)
    keys = dict(reward=REWARD, action=ACTION, sample_log_prob=LOG_PROB, value=VALUE, advantage=ADVANTAGE,
                value_target=VALUE_TARGET, done="done", terminated="terminated", loc=LOC, scale=SCALE)
    if cls is DistillationPPOLoss:
        keys.update(teacher_loc=TEACHER_LOC, teacher_scale=TEACHER_SCALE)
    loss.set_keys(**keys)
    loss.make_value_estimator(gamma=0.99, lmbda=0.95)
    return loss


@pytest.fixture(scope="module")
def setup():
    _, models, batch = tiny_models_and_batch()
    batch[TEACHER_LOC] = batch[LOC] + SHIFT
    batch[TEACHER_SCALE] = batch[SCALE] * SCALE_RATIO
    with torch.no_grad():
        _loss(PopArtMAPPOLoss, models).value_estimator(batch)
    return models, batch.reshape(-1)


def _expected_forward_kl(batch) -> torch.Tensor:
    """KL(teacher || student) by hand: Gaussians on the continuous entries, Bernoulli on the gripper."""
    mu_s, s_s = batch[LOC], batch[SCALE]
    mu_t, s_t = batch[TEACHER_LOC], batch[TEACHER_SCALE]
    cont = [i for i in range(mu_s.shape[-1]) if i != GRASP_ENTRY]
    gauss = (torch.log(s_s / s_t) + (s_t**2 + (mu_t - mu_s) ** 2) / (2 * s_s**2) - 0.5)[..., cont].sum(-1)
    p, q = torch.sigmoid(mu_t[..., GRASP_ENTRY]), torch.sigmoid(mu_s[..., GRASP_ENTRY])
    bern = p * torch.log(p / q) + (1 - p) * torch.log((1 - p) / (1 - q))
    return (gauss + bern).mean()


def test_forward_kl_matches_the_hand_computed_value(setup):
    models, batch = setup
    out = _loss(DistillationPPOLoss, models, beta=2.0)(batch)
    expected = _expected_forward_kl(batch)
    torch.testing.assert_close(out["kl_teacher"], expected, rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(out["loss_distill"].detach(), 2.0 * expected, rtol=1e-4, atol=1e-6)
    assert float(expected) > 0.01
    reverse = _loss(DistillationPPOLoss, models, direction="reverse")(batch)["kl_teacher"]
    assert float(reverse) > 0 and abs(float(reverse) - float(expected)) > 1e-3  # KL is not symmetric


def test_beta_zero_is_the_mappo_loss(setup):
    models, batch = setup
    torch.manual_seed(1)
    mappo = _loss(PopArtMAPPOLoss, models)(batch)
    torch.manual_seed(1)  # the TanhNormal entropy is estimated from a sample
    distill = _loss(DistillationPPOLoss, models, beta=0.0)(batch)
    for key in ("loss_objective", "loss_critic", "loss_entropy", "kl"):
        torch.testing.assert_close(distill[key], mappo[key])
    assert float(distill["loss_distill"].detach()) == 0.0


def test_the_kl_term_pulls_the_student_towards_the_teacher(setup):
    models, batch = setup
    state = {k: v.clone() for k, v in models.actor.state_dict().items()}
    loss = _loss(DistillationPPOLoss, models, beta=1.0)
    opt = torch.optim.Adam(models.actor.parameters(), lr=1e-2)
    first = None
    for _ in range(30):
        out = loss(batch)
        first = float(out["kl_teacher"]) if first is None else first
        opt.zero_grad()
        out["loss_distill"].backward()
        opt.step()
    assert float(loss(batch)["kl_teacher"]) < 0.5 * first
    models.actor.load_state_dict(state)


def test_bad_arguments_are_named(setup):
    models, _ = setup
    with pytest.raises(ValueError, match="'sideways'"):
        _loss(DistillationPPOLoss, models, direction="sideways")
    with pytest.raises(ValueError, match="beta must be >= 0, got -1"):
        _loss(DistillationPPOLoss, models, beta=-1.0)
