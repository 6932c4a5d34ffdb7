"""TorchRL losses of the project (installed as ``pnp.losses``): MAPPO with a PopArt critic
head, teacher-student distillation, and the action distribution with a binary gripper."""
from __future__ import annotations

from .distillation import DistillationPPOLoss
from .distributions import TanhNormalGripper, bernoulli_kl
from .mappo import PopArtMAPPOLoss, policy_kl

__all__ = ["DistillationPPOLoss", "PopArtMAPPOLoss", "TanhNormalGripper", "bernoulli_kl", "policy_kl"]
