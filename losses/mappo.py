"""MAPPO with a PopArt critic head, as a TorchRL ``LossModule``.

:class:`PopArtMAPPOLoss` is TorchRL's ``MAPPOLoss`` (clipped PPO, multi-agent GAE,
advantages normalised per agent) whose critic ends in a PopArt head: the critic loss is
taken in the head's normalised space, and the head's statistics move once per iteration
in :meth:`PopArtMAPPOLoss.update_value_norm`, preserving the critic's outputs, never
inside ``forward``. ``forward`` also returns ``kl``, the mean KL divergence from the
behaviour policy (whose ``loc``/``scale`` the batch carries) to the current one, which a
KL-adaptive learning rate reads.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import ProbabilisticTensorDictSequential, TensorDictModule
from tensordict.utils import NestedKey
from torch import distributions as D
from torch import nn
from torchrl.modules.value_norm import ValueNorm
from torchrl.objectives import MAPPOLoss

from .distributions import TanhNormalGripper, bernoulli_kl

__all__ = ["PopArtMAPPOLoss", "policy_kl"]


class _PopArtView(ValueNorm):
    """A PopArt head's statistics as MAPPOLoss sees them: read-only, so that ``forward``
    (which calls ``update`` on every minibatch) cannot move them."""

    def __init__(self, popart: nn.Module):
        super().__init__(shape=1)
        self.__dict__["popart"] = popart  # not a submodule: its state lives in the critic

    def update(self, value_target):
        pass

    def normalize(self, value_target):
        return self.popart.stats.normalize(value_target)

    def denormalize(self, normalised_value):
        return self.popart.stats.denormalize(normalised_value)

    def scale(self):
        return self.popart.stats.scale()


def policy_kl(old: D.Distribution, new: D.Distribution) -> torch.Tensor:
    """KL(old || new) per sample, summed over action entries: the pre-tanh Gaussians'
    (tanh is a bijection, so the TanhNormal KL equals it), plus the gripper Bernoulli's."""
    if isinstance(old, TanhNormalGripper):
        return old.kl_to(new)
    a, b = old.base_dist, new.base_dist  # TanhNormal: a transformed Normal
    while isinstance(a, D.Independent):
        a, b = a.base_dist, b.base_dist
    return D.kl_divergence(D.Normal(a.loc, a.scale), D.Normal(b.loc, b.scale)).sum(-1)


class PopArtMAPPOLoss(MAPPOLoss):
    """MAPPO whose critic's last module is a PopArt head (``popart``, or ``None`` for
    plain value regression).

    Args:
        actor_network: a ``ProbabilisticActor`` writing ``loc`` and ``scale``.
        critic_network: the critic, ending in ``popart`` when one is given.
        popart: a module with ``stats`` (a ``PopArtValueNorm``) and ``update(targets)``
            that rescales its own affine map (``pnp.training.models.PopArt``).
        **kwargs: ``MAPPOLoss`` arguments (``clip_epsilon``, ``entropy_coeff``, ...).

    Returns from ``forward`` the ``loss_objective``, ``loss_critic`` and ``loss_entropy``
    entries, TorchRL's diagnostics (``clip_fraction``, ``kl_approx``, ``entropy``,
    ``explained_variance``, ...), and ``kl``.
    """

    @dataclass
    class _AcceptedKeys(MAPPOLoss._AcceptedKeys):
        """MAPPOLoss's keys plus the behaviour policy's distribution parameters."""

        loc: NestedKey = "loc"
        scale: NestedKey = "scale"

    default_keys = _AcceptedKeys

    def __init__(self, actor_network: ProbabilisticTensorDictSequential, critic_network: TensorDictModule,
                 popart: nn.Module | None = None, **kwargs):
        super().__init__(actor_network, critic_network, value_norm=_PopArtView(popart) if popart is not None else None,
                         functional=False,  # PopArt rescales the critic's own parameters in place
                         **kwargs)
        self.__dict__["popart"] = popart  # a part of the critic, registered there

    @torch.no_grad()
    def update_value_norm(self, tensordict: TensorDictBase) -> None:
        """Move the PopArt statistics to the batch's value targets (once per iteration,
        after the value estimator wrote them)."""
        if self.popart is not None:
            self.popart.update(tensordict.get(self.tensor_keys.value_target))

    @torch.no_grad()
    def behaviour_dist(self, tensordict: TensorDictBase) -> D.Distribution:
        """The behaviour policy's distribution from the loc and scale the batch recorded."""
        k = self.tensor_keys
        return self.actor_network.module[-1].get_dist(tensordict.select(k.loc, k.scale))

    def _get_cur_log_prob(self, tensordict: TensorDictBase, params=None):
        # TorchRL's extension point for the current policy's log-probability: its distribution
        # is kept, so that the KL below needs no second actor forward (~15 % of an update).
        log_prob, dist, is_composite = super()._get_cur_log_prob(tensordict, params)
        if params is None:  # the current parameters, not a delayed actor's
            self.__dict__["_current"] = dist
        return log_prob, dist, is_composite

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        behaviour = tensordict.select(self.tensor_keys.loc, self.tensor_keys.scale)
        self.__dict__["_current"] = None
        out = super().forward(tensordict)
        current = self.__dict__.pop("_current")
        if current is None:
            raise RuntimeError("MAPPOLoss.forward did not build the current policy's distribution "
                               "through _get_cur_log_prob (a TorchRL change?)")
        old = self.behaviour_dist(behaviour)
        out.set("kl", policy_kl(old, current).mean().detach())
        if isinstance(current, TanhNormalGripper):  # which part of the policy the KL (and so the lr) answers to
            out.set("kl_gripper", bernoulli_kl(old.gripper.logits, current.gripper.logits).mean().detach())
        return self._extend(out, tensordict, current)

    def _extend(self, out: TensorDictBase, tensordict: TensorDictBase, current: D.Distribution) -> TensorDictBase:
        """Hook for subclasses: more ``loss_*`` terms from the current policy's distribution."""
        return out
