"""Teacher-student distillation as a TorchRL ``LossModule`` (paper Sec. III-C).

The student is trained by PPO on its own rollouts (the MAPPO loss, with its rewards at
fixed scales) plus ``beta`` times the KL divergence between the frozen teacher's action
distribution and its own, as in the work the paper cites for it (Liu et al. 2022, simulated
humanoid football): RL with a KL regulariser towards the teacher, not behaviour cloning.
The teacher's distribution parameters are written into the batch when it is collected
(``teacher_loc``, ``teacher_scale``: the teacher acts on its own clean observations), so
the loss needs no teacher forward. Both parts of the action distribution have an analytic
KL: the pre-tanh Gaussians' (tanh is a bijection) and the gripper Bernoulli's.
"""
from __future__ import annotations

from dataclasses import dataclass

from tensordict import TensorDictBase
from tensordict.nn import ProbabilisticTensorDictSequential, TensorDictModule
from tensordict.utils import NestedKey
from torch import distributions as D
from torch import nn

from .mappo import PopArtMAPPOLoss, policy_kl

__all__ = ["DistillationPPOLoss"]

DIRECTIONS = ("forward", "reverse")


class DistillationPPOLoss(PopArtMAPPOLoss):
    """:class:`PopArtMAPPOLoss` plus ``loss_distill = beta * mean KL`` to the teacher.

    Args:
        beta: weight of the KL term (0: the MAPPO loss alone); an attribute, so a schedule
            can anneal it between iterations.
        direction: ``"forward"`` KL(teacher || student), mass-covering, the default;
            ``"reverse"`` KL(student || teacher).
        actor_network, critic_network, popart, **kwargs: as :class:`PopArtMAPPOLoss`.

    Logs ``kl_teacher`` (the KL before ``beta``).
    """

    @dataclass
    class _AcceptedKeys(PopArtMAPPOLoss._AcceptedKeys):
        """PopArtMAPPOLoss's keys plus the teacher's distribution parameters."""

        teacher_loc: NestedKey = "teacher_loc"
        teacher_scale: NestedKey = "teacher_scale"

    default_keys = _AcceptedKeys

    def __init__(self, actor_network: ProbabilisticTensorDictSequential, critic_network: TensorDictModule,
                 popart: nn.Module | None = None, *, beta: float = 1.0, direction: str = "forward", **kwargs):
        if direction not in DIRECTIONS:
            raise ValueError(f"direction must be one of {DIRECTIONS}, got {direction!r}")
        if beta < 0:
            raise ValueError(f"beta must be >= 0, got {beta}")
        super().__init__(actor_network, critic_network, popart, **kwargs)
        self.beta, self.direction = float(beta), direction

    def teacher_dist(self, tensordict: TensorDictBase) -> D.Distribution:
        """The teacher's distribution from the parameters stored in the batch."""
        k = self.tensor_keys
        params = tensordict.select(k.teacher_loc, k.teacher_scale).rename_key_(k.teacher_loc, k.loc)
        return self.actor_network.module[-1].get_dist(params.rename_key_(k.teacher_scale, k.scale))

    def _extend(self, out: TensorDictBase, tensordict: TensorDictBase, current: D.Distribution) -> TensorDictBase:
        teacher = self.teacher_dist(tensordict)
        kl = policy_kl(teacher, current) if self.direction == "forward" else policy_kl(current, teacher)
        kl = kl.mean()
        out.set("loss_distill", self.beta * kl)
        out.set("kl_teacher", kl.detach())
        return out
