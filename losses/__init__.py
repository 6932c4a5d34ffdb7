"""TorchRL losses of the project (installed as ``pnp.losses``): MAPPO with a PopArt critic
head, Erskine et al.'s per-stage mixed advantage (a Table I baseline), teacher-student
distillation, and the action distribution with a binary gripper."""
from __future__ import annotations

from .distillation import DistillationPPOLoss
from .distributions import TanhNormalGripper, bernoulli_kl
from .erskine import CooperativeMAPPOLoss
from .mappo import PopArtMAPPOLoss, policy_kl

__all__ = [
    "CooperativeMAPPOLoss", "DistillationPPOLoss", "PopArtMAPPOLoss", "TanhNormalGripper", "bernoulli_kl", "policy_kl",
]
