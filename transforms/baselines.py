"""Reward schedules of the per-stage baselines, at the fixed scales mu_j of Table II.

* :class:`StageRewards` (Erskine et al., cooperative consecutive policies): beside the
  :class:`~pnp.transforms.FixedScales` reward it writes each stage's own reward side by
  side, the reward the critic of that stage learns.
* :class:`SequentialSubtask` (Bendikas et al., one policy per sub-task trained in turn):
  sub-task k pays the terms of stages <= k, and its episodes end with success at S_{k+1}.

Both take the :class:`~pnp.transforms.StageRewardSchedule` arguments and, like it, read
the raw terms and the stage written by :class:`~pnp.transforms.StageTransition`; they
replace the schedule at the end of the ``Compose``.
"""
from __future__ import annotations

from typing import Mapping

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey, unravel_key
from torchrl.data import Composite, Unbounded

from ._checks import _check_exact, _get
from ._reward_scaling import FixedScales
from ._stage import _set_nested

__all__ = ["SequentialSubtask", "StageRewards"]


def _active_terms(schedule: FixedScales, terms: torch.Tensor, stage: torch.Tensor) -> torch.Tensor:
    """The terms as the schedule's reward sees them: stage progress filled in, gated terms
    zero below their stage (as ``StageRewardSchedule._reward``)."""
    if schedule._progress_col >= 0:
        terms = terms.clone()
        terms[..., schedule._progress_col] = stage.to(terms.dtype)
    return terms * (stage.unsqueeze(-1) >= schedule._gate).to(terms.dtype)


def _best_steps(schedule: FixedScales, high: Mapping[str, float]) -> torch.Tensor:
    """``mu_j max(high_j, 0)`` per stage-wise term of ``schedule`` (its best step's share)."""
    staged = {n: v for n, v in high.items() if n in schedule.mu}
    _check_exact("high", staged, schedule.stage_term_names)
    return torch.tensor([schedule.mu[n] * max(float(staged[n]), 0.0) for n in schedule.stage_term_names])


class StageRewards(FixedScales):
    """The fixed-scale reward, plus each stage's reward in its own column.

    Writes ``stage_rewards_key``, float ``[*B, A, n_stages]``: column i is R_fixed plus
    ``sum_j mu_j r_j`` over the terms of stage i while the robot is in stage i; in every
    stage above i it is ``completed_share * sum_j mu_j max(high_j, 0)`` over stage i's terms
    (a completed sub-task keeps paying its best step), and 0 below i. A term is thus paid
    only in its own stage, as LiuMax/LiuMin activate it, and every stage's sub-task pays its
    own penalties. ``reward_key`` keeps the FixedScales reward (logged; Erskine's loss reads
    the columns).

    Why the completed pay: the stage terms are positive, so with 0 above i critic i values
    hovering in stage i forever over completing it (Erskine et al.'s sub-task critics end at
    completion; their rewards were not positive kernels). Paid per step rather than once,
    a robot that falls back loses it again, so re-entering a stage earns nothing twice.
    ``completed_share=0`` is the column without it.

    Args:
        high: upper bound of every stage-wise term's raw value (``pnp.task.terms.REWARD_TABLE``);
            needed when ``completed_share > 0``.
        completed_share: the share of a stage's best step paid above it.
        **cfg: the :class:`~pnp.transforms.StageRewardSchedule` arguments.
    """

    def __init__(self, *, high: Mapping[str, float] | None = None, completed_share: float = 0.0,
                 stage_rewards_key: NestedKey = ("agents", "stage_rewards"), **cfg):
        super().__init__(**cfg)
        if not completed_share >= 0.0:
            raise ValueError(f"completed_share must be >= 0, got {completed_share}")
        best = torch.zeros(len(self.stage_term_names))
        if completed_share > 0.0:
            if high is None:
                raise ValueError("completed_share > 0 needs `high`, the bound of every stage-wise term")
            best = _best_steps(self, high)
        completed = torch.zeros(self.n_stages).index_add_(0, self._term_stage, best) * float(completed_share)
        self.register_buffer("_completed", completed, persistent=False)
        self.register_buffer("_stage_ids", torch.arange(self.n_stages), persistent=False)
        self.stage_rewards_key = unravel_key(stage_rewards_key)
        self.out_keys = [*self.out_keys, self.stage_rewards_key]

    def stage_rewards(self, terms: torch.Tensor, stage: torch.Tensor) -> torch.Tensor:
        """``[*B, A, n_stages]`` from the raw terms ``[*B, A, T]`` and the stage ``[*B, A]``."""
        terms = _active_terms(self, terms, stage)
        staged = self._mu.to(terms.dtype) * terms[..., self._stage_idx]
        own = terms.new_zeros(*stage.shape, self.n_stages).index_add_(-1, self._term_stage, staged)
        fixed = (self._fixed_w.to(terms.dtype) * terms[..., self._fixed_idx]).sum(-1, keepdim=True)
        here = torch.nn.functional.one_hot(stage, self.n_stages).to(terms.dtype)
        above = (self._stage_ids < stage.unsqueeze(-1)).to(terms.dtype)
        return here * (own + fixed) + above * self._completed.to(terms.dtype)

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        next_tensordict = super()._step(tensordict, next_tensordict)
        terms, stage = self._read(next_tensordict)
        next_tensordict.set(self.stage_rewards_key, self.stage_rewards(terms, stage))
        return next_tensordict

    def transform_reward_spec(self, reward_spec: Composite) -> Composite:
        reward_spec = super().transform_reward_spec(reward_spec)
        if self.stage_rewards_key not in reward_spec.keys(True, True):
            reward = reward_spec[self.reward_key]
            spec = Unbounded(shape=(*reward.shape[:-1], self.n_stages), dtype=reward.dtype, device=reward.device)
            _set_nested(reward_spec, self.stage_rewards_key, spec, like=self.parent.full_observation_spec)
        return reward_spec


class SequentialSubtask(FixedScales):
    """Sub-task ``subtask`` = k of a sequence trained in turn (Bendikas et al.).

    Reward: R_fixed plus ``mu_j r_j`` over the terms of stages <= k (the later stages'
    terms weigh 0). When every robot of a world has reached S_{k+1}, its episode ends there
    with success: ``done``, ``terminated`` and ``success`` are set, ``episode_stage`` records
    the stage, ``success_step`` the step, and each robot's reward gains the success bonus
    ``success_bonus * sum_j mu_j max(high_j, 0) / (1 - gamma)`` over the sub-task's terms
    (the return of its best per-step reward forever: ending at success never pays less
    than hovering short of it). The last stage's sub-task is the whole task: the
    FixedScales reward, and the env's own episode ends.

    Args:
        subtask: k, a buffer (in the state dict); :meth:`set_subtask` moves it on.
        high: upper bound of every stage-wise term's raw value (``pnp.task.terms.REWARD_TABLE``).
        gamma: the discount the bonus is measured with.
        success_bonus: its share (0: none).
        **cfg: the :class:`~pnp.transforms.StageRewardSchedule` arguments.
    """

    def __init__(self, *, subtask: int = 0, high: Mapping[str, float], gamma: float, success_bonus: float = 1.0,
                 done_key: NestedKey = "done", terminated_key: NestedKey = "terminated",
                 truncated_key: NestedKey = "truncated", success_key: NestedKey = "success",
                 success_step_key: NestedKey = "success_step", step_count_key: NestedKey = "step_count", **cfg):
        super().__init__(**cfg)
        if not 0.0 <= gamma < 1.0:
            raise ValueError(f"gamma must be in [0, 1), got {gamma}")
        if not success_bonus >= 0.0:
            raise ValueError(f"success_bonus must be >= 0, got {success_bonus}")
        best = _best_steps(self, high)
        bonus = [success_bonus * float(best[self._term_stage <= k].sum()) / (1.0 - gamma) for k in range(self.n_stages)]
        self.register_buffer("_bonus", torch.tensor(bonus), persistent=False)
        self.done_key, self.terminated_key = unravel_key(done_key), unravel_key(terminated_key)
        self.truncated_key, self.success_key = unravel_key(truncated_key), unravel_key(success_key)
        self.success_step_key, self.step_count_key = unravel_key(success_step_key), unravel_key(step_count_key)
        self.register_buffer("subtask", torch.zeros((), dtype=torch.long))
        self.set_subtask(subtask)

    def set_subtask(self, k: int) -> None:
        if not 0 <= int(k) < self.n_stages:
            raise ValueError(f"subtask must be in [0, {self.n_stages}), got {k}")
        self.subtask.fill_(int(k))

    @property
    def bonus(self) -> float:
        """The success bonus of the current sub-task (0 for the last: it has no S_{k+1})."""
        k = int(self.subtask)
        return float(self._bonus[k]) if k < self.n_stages - 1 else 0.0

    def _coefficients(self, stage):
        return self._mu * (self._term_stage <= self.subtask), self._mu.new_zeros(())

    def _end_at_next_stage(self, next_td: TensorDictBase) -> torch.Tensor:
        """Ends (with success) the episodes whose robots all reached S_{k+1}; returns them, bool [*B]."""
        stage = _get(next_td, self.stage_key, "step output")  # [*B, A, 1]
        reached = (stage > self.subtask).flatten(-2).all(-1)
        flag = reached.unsqueeze(-1)
        for key in (self.done_key, self.terminated_key, self.success_key):
            next_td.set(key, _get(next_td, key, "step output") | flag)
        truncated = next_td.get(self.truncated_key, None)
        if truncated is not None:  # a terminated episode is not also truncated (as the env writes them)
            next_td.set(self.truncated_key, truncated & ~flag)
        final = _get(next_td, self.episode_stage_key, "step output")
        next_td.set(self.episode_stage_key, torch.where(flag.unsqueeze(-1), stage, final))
        step, count = next_td.get(self.success_step_key, None), next_td.get(self.step_count_key, None)
        if step is not None and count is not None:
            next_td.set(self.success_step_key, torch.where(flag & (step < 0), count.to(step.dtype), step))
        return reached

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        if int(self.subtask) == self.n_stages - 1:
            return super()._step(tensordict, next_tensordict)
        reached = self._end_at_next_stage(next_tensordict)  # before the reward: it counts the ended episodes
        next_tensordict = super()._step(tensordict, next_tensordict)
        reward = next_tensordict.get(self.reward_key)
        bonus = self.bonus * reached.to(reward.dtype)
        next_tensordict.set(self.reward_key, reward + bonus.reshape(*bonus.shape, 1, 1))
        return next_tensordict
