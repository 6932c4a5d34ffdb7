"""TorchRL transforms of the dynamic reward curriculum (installed as ``pnp.transforms``)."""
from __future__ import annotations

from ._reward_scaling import (
    SCHEDULES,
    AdaptiveRewardScaling,
    FixedScales,
    LiuMax,
    LiuMin,
    StageRewardSchedule,
    make_reward_schedule,
)
from ._stage import StageTransition

__all__ = [
    "SCHEDULES",
    "AdaptiveRewardScaling",
    "FixedScales",
    "LiuMax",
    "LiuMin",
    "StageRewardSchedule",
    "StageTransition",
    "make_reward_schedule",
]
