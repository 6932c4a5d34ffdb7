"""TorchRL losses of the project (installed as ``pnp.losses``): MAPPO with a PopArt critic
head, and the action distribution with a binary gripper."""
from __future__ import annotations

from .distributions import TanhNormalGripper, bernoulli_kl
from .mappo import PopArtMAPPOLoss, policy_kl

__all__ = ["PopArtMAPPOLoss", "TanhNormalGripper", "bernoulli_kl", "policy_kl"]
