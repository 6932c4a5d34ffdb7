"""TorchRL transforms of the dynamic reward curriculum (installed as ``pnp.transforms``).

Needs only torch, torchrl and tensordict (the base install; mujoco and the recipes' tools
are extras). Per-robot entries live in a group, ``"agents"`` by default, of batch
``[*B, A]``: ``B`` the env batch, ``A`` the robots; an entry of another shape is a
``ValueError`` naming its key, the shape seen and the shape expected. The transforms run
in an env (alone, in a ``Compose``, in ``SerialEnv``/``ParallelEnv``, in a collector) or
called directly on a tensordict holding t and ``"next"``; a replay buffer is refused
(``RuntimeError``): their state is per env world, and sampled rows have no world, so
compute stages and rewards in the env and store them.
``ObservationNoise`` adds per-field Gaussian noise and held-value dropouts to observations.
``ColumnHistory`` appends the last few values of some observation columns, dropping others.
"""
from __future__ import annotations

from ._graph import StageGraph
from ._history import ColumnHistory
from ._noise import ObservationNoise
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
    "ColumnHistory",
    "FixedScales",
    "LiuMax",
    "LiuMin",
    "ObservationNoise",
    "StageGraph",
    "StageRewardSchedule",
    "StageTransition",
    "make_reward_schedule",
]
