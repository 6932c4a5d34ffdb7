"""Erskine et al.'s cooperative consecutive policies in PPO, as a TorchRL ``LossModule``.

Erskine et al. (RA-L 2022, after Cooperative SAC) train one policy and one critic per
sub-task at once; critic i learns sub-task i's reward, and policy i maximises a convex
mix of its own and the next sub-task's critic, so that it hands over in states the next
policy values. The original is off-policy (soft Q-functions, ``(1 - c) Q_i + c Q_{i+1}``).
Our on-policy reading: critic i is a state-value function of stage i's reward (the
``StageRewards`` columns: stage i's terms and R_fixed, paid while the robot is in stage
i, and with ``completed_share`` stage i's best step in every later stage), every critic
values every state, one GAE per critic gives ``A_i``, and each sample's
policy-gradient advantage is that of its stage s,

    A = (1 - c) A_s + c A_{s+1}        (A_{s+1} := A_s in the last stage),

normalised per agent as MAPPO does. The sample's log-probability comes from its stage's
actor (``pnp.training.stage_ensemble.StageEnsemble``); the critic loss regresses every
critic on its own value target.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import ProbabilisticTensorDictSequential, TensorDictModule
from tensordict.utils import NestedKey, unravel_key
from torch import nn
from torchrl.objectives.value import MultiAgentGAE

from .mappo import PopArtMAPPOLoss

__all__ = ["CooperativeGAE", "CooperativeMAPPOLoss", "mixed_advantage"]


def mixed_advantage(per_stage: torch.Tensor, stage: torch.Tensor, mix: float) -> torch.Tensor:
    """``(1 - mix) A_s + mix A_{s+1}`` per sample: ``per_stage`` ``[..., n_stages]``,
    ``stage`` ``[..., 1]`` (integer); returns ``[..., 1]``. The last stage has no next one
    and keeps its own advantage."""
    last = per_stage.shape[-1] - 1
    s = stage.long()
    if bool(((s < 0) | (s > last)).any()):
        raise ValueError(f"stage outside [0, {last}]: {sorted(set(s.reshape(-1).tolist()))}")
    own, nxt = per_stage.gather(-1, s), per_stage.gather(-1, (s + 1).clamp(max=last))
    return (1.0 - mix) * own + mix * nxt


class CooperativeGAE(MultiAgentGAE):
    """GAE of every stage's critic on its own reward column, then the mixed advantage.

    Reads the per-stage rewards ``("next", reward)`` and values ``[*B, T, A, n_stages]``
    and the stage at t (``stage_key``, ``[*B, T, A, 1]``). Writes ``value_target`` (one per
    critic), ``stage_advantage_key`` (``A_i`` for every i) and ``advantage`` (the mix).

    Args:
        mix: c in [0, 1].
        stage_key, stage_advantage_key: the stage read and the per-stage advantages written.
        **kwargs: ``MultiAgentGAE`` arguments (``gamma``, ``lmbda``, ``value_network``, ...).
    """

    def __init__(self, *, mix: float, stage_key: NestedKey = ("agents", "stage"),
                 stage_advantage_key: NestedKey = ("agents", "stage_advantage"), **kwargs):
        if not 0.0 <= mix <= 1.0:
            raise ValueError(f"mix (Erskine's c) must be in [0, 1], got {mix}")
        super().__init__(**kwargs)
        self.mix = float(mix)
        self.stage_key, self.stage_advantage_key = unravel_key(stage_key), unravel_key(stage_advantage_key)

    def _prepare_signals(self, reward, done, terminated, value):
        reward, done, terminated = super()._prepare_signals(reward, done, terminated, value)
        # The team's done is every critic's: broadcast it over the stage columns too.
        return reward, done.expand(value.shape), terminated.expand(value.shape)

    def forward(self, tensordict: TensorDictBase, **kwargs) -> TensorDictBase:
        tensordict = super().forward(tensordict, **kwargs)
        per_stage = tensordict.get(self.tensor_keys.advantage)
        if per_stage.shape[-1] < 2:
            raise ValueError(f"CooperativeGAE needs one value per stage; the critic gave {per_stage.shape[-1]} "
                             "(build it with model.per_stage=erskine)")
        tensordict.set(self.stage_advantage_key, per_stage)
        tensordict.set(self.tensor_keys.advantage, mixed_advantage(per_stage, tensordict.get(self.stage_key), self.mix))
        return tensordict


class CooperativeMAPPOLoss(PopArtMAPPOLoss):
    """:class:`PopArtMAPPOLoss` with per-stage critics and the mixed advantage of
    :class:`CooperativeGAE` (its value estimator).

    Args:
        mix: Erskine's c, the weight of the next stage's advantage (0.5 in the paper we compare with).
        actor_network: a ``StageEnsemble`` actor routed by stage.
        critic_network: a ``StageEnsemble`` critic with ``concat=True`` (one value per stage).
        popart: the critic's PopArt head, one statistic per stage, or ``None``.
        **kwargs: ``MAPPOLoss`` arguments.

    ``forward`` returns what :class:`PopArtMAPPOLoss` returns; ``loss_critic`` averages
    over the stage critics.
    """

    @dataclass
    class _AcceptedKeys(PopArtMAPPOLoss._AcceptedKeys):
        """PopArtMAPPOLoss's keys plus the per-stage rewards, the stage, and the per-stage advantages."""

        stage_rewards: NestedKey = ("agents", "stage_rewards")
        stage: NestedKey = ("agents", "stage")
        stage_advantage: NestedKey = ("agents", "stage_advantage")

    default_keys = _AcceptedKeys

    def __init__(self, actor_network: ProbabilisticTensorDictSequential, critic_network: TensorDictModule,
                 popart: nn.Module | None = None, *, mix: float = 0.5, **kwargs):
        if not 0.0 <= mix <= 1.0:
            raise ValueError(f"mix (Erskine's c) must be in [0, 1], got {mix}")
        super().__init__(actor_network, critic_network, popart, **kwargs)
        self.mix = float(mix)

    def make_value_estimator(self, value_type=None, **hyperparams):
        if value_type is not None:
            raise ValueError(f"{type(self).__name__} uses its CooperativeGAE; got value_type={value_type!r}")
        k = self.tensor_keys
        estimator = CooperativeGAE(mix=self.mix, stage_key=k.stage, stage_advantage_key=k.stage_advantage,
                                   value_network=self.critic_network, **hyperparams)
        super().make_value_estimator(estimator)
        self._forward_value_estimator_keys()
        return self

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        # As LossModule's, but the estimator's reward is the per-stage columns.
        estimator = getattr(self, "_value_estimator", None)
        if estimator is not None:
            k = self.tensor_keys
            estimator.set_keys(advantage=k.advantage, value_target=k.value_target, value=k.value,
                               reward=k.stage_rewards, done=k.done, terminated=k.terminated)
            estimator.stage_key, estimator.stage_advantage_key = unravel_key(k.stage), unravel_key(k.stage_advantage)
        self._set_in_keys()
