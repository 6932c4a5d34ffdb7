"""Stage-wise reward schedules: the paper's adaptive scaling and its baselines.

All schedules write, per robot,
``reward = sum_f w_f r_f + sum_j (a_j r_j + c_j)`` over fixed terms f and stage-wise
terms j (paper Eq. 1), and differ only in the coefficients ``a_j, c_j``:

* :class:`AdaptiveRewardScaling` (``"dynamic"``): ``a_j = rho_j``, updated across
  episodes by Eq. 2, ``c_j = 0``.
* :class:`FixedScales` (``"fixed"``): ``a_j = mu_j``.
* :class:`LiuMax` / :class:`LiuMin` (``"liu_max"``/``"liu_min"``), our reading of Liu et
  al. (Visual whole-body control for legged loco-manipulation) as ablated in the paper:
  in stage s, terms of stage s are active (``a_j = mu_j``); terms of completed stages
  (stage < s) are deactivated and replaced by the constant ``c_j = mu_j * high_j`` (max)
  or ``mu_j * low_j`` (min); terms of later stages give 0.

They read the raw terms (float ``[*B, A, T]``), the current stage and the
episode-final stage written by :class:`~pnp.transforms.StageTransition`, which must come
before them in a ``Compose``.
"""
from __future__ import annotations

from typing import Mapping, Sequence

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey, unravel_key
from torchrl.data import Composite, Unbounded
from torchrl.envs.transforms import Transform

from ._checks import _check_agent_shape, _check_group_batch, _ClonesOwnBuffers, _check_exact, _check_names, _EnvOnly, _get, _LazyBuffers
from ._stage import _ResetKeysMixin, _set_nested, _slot_reset_mask

__all__ = [
    "AdaptiveRewardScaling",
    "FixedScales",
    "LiuMax",
    "LiuMin",
    "StageRewardSchedule",
    "make_reward_schedule",
]


class StageRewardSchedule(_ClonesOwnBuffers, _ResetKeysMixin, _EnvOnly, Transform):
    """Base class: term bookkeeping, the reward sum and the episode-end stage histogram.

    Args:
        term_names: names of the columns of ``terms_key``, in order.
        term_stage: stage-wise term -> its stage index; every other term is fixed.
        mu: stage-wise term -> ``mu_j > 0`` (Table II).
        fixed_weights: fixed term -> constant weight (may be negative).
        n_stages: number of stages (default: highest term stage + 1).
        stage_progress_term: a term whose value is replaced by the current stage index
            (Table II "stage progress": only the curriculum knows the stage).
        stage_gates: term -> min stage; the term counts only when ``stage >= min``.

    Per-robot entries have shape ``[*B, A, ...]`` (``B`` the env batch), else ``ValueError``.
    Not for replay buffers: the state is per env world and robot, a sampled batch has no
    world identity (rho would be sized to the first sample, never move, and be applied to
    rows by position), so ``forward`` refuses there (eval mode, no env): compute rewards in
    the env and store them.
    """

    _own_keys: frozenset[str] = frozenset()
    _needs_env = "its state (rho, the stage histogram) is per env world and robot"
    _instead = (
        "Compute the rewards in the env (TransformedEnv(env, Compose(StageTransition(...), "
        "schedule))) and store them."
    )

    def __init__(
        self,
        term_names: Sequence[str],
        term_stage: Mapping[str, int],
        mu: Mapping[str, float],
        fixed_weights: Mapping[str, float] | None = None,
        n_stages: int | None = None,
        stage_progress_term: str | None = None,
        stage_gates: Mapping[str, int] | None = None,
        terms_key: NestedKey = ("agents", "reward_terms"),
        stage_key: NestedKey = ("agents", "stage"),
        episode_stage_key: NestedKey = ("agents", "episode_stage"),
        reward_key: NestedKey = ("agents", "reward"),
        reset_keys: Sequence[NestedKey] | None = None,
    ):
        self.terms_key, self.stage_key = unravel_key(terms_key), unravel_key(stage_key)
        self.episode_stage_key = unravel_key(episode_stage_key)
        self.reward_key = unravel_key(reward_key)
        super().__init__(in_keys=[self.terms_key, self.stage_key], out_keys=[self.reward_key])
        self._init_reset_keys(reset_keys)
        names = tuple(term_names)
        fixed_weights = dict(fixed_weights or {})
        stage_gates = dict(stage_gates or {})
        _check_names("term_names", names, names, unique=True)
        _check_names("term_stage", term_stage, names)
        _check_names("stage_gates", stage_gates, names)
        if stage_progress_term is not None:
            _check_names("stage_progress_term", [stage_progress_term], names)
        stage_terms = tuple(n for n in names if n in term_stage)
        fixed_terms = tuple(n for n in names if n not in term_stage)
        _check_exact("mu", mu, stage_terms)
        _check_exact("fixed_weights", fixed_weights, fixed_terms)
        if n_stages is None:
            n_stages = max(term_stage.values(), default=0) + 1
        self.n_stages = int(n_stages)
        for n in stage_terms:
            if not 0 <= term_stage[n] < self.n_stages:
                raise ValueError(
                    f"term_stage[{n!r}]={term_stage[n]} not in [0, {self.n_stages})"
                )
            if not mu[n] > 0:
                raise ValueError(f"mu[{n!r}] must be > 0, got {mu[n]}")
        self.term_names, self.stage_term_names, self.fixed_term_names = names, stage_terms, fixed_terms
        self.term_stage = {n: int(term_stage[n]) for n in stage_terms}
        self.mu = {n: float(mu[n]) for n in stage_terms}
        self.fixed_weights = {n: float(fixed_weights[n]) for n in fixed_terms}
        self.stage_progress_term, self.stage_gates = stage_progress_term, stage_gates
        # Lookup tensors (not state): columns of stage-wise and fixed terms, gates.
        idx = {n: i for i, n in enumerate(names)}
        lookups = {
            "_stage_idx": [idx[n] for n in stage_terms],
            "_fixed_idx": [idx[n] for n in fixed_terms],
            "_term_stage": [self.term_stage[n] for n in stage_terms],
            "_gate": [stage_gates.get(n, 0) for n in names],
        }
        for name, values in lookups.items():
            self.register_buffer(name, torch.tensor(values, dtype=torch.long), persistent=False)
        fixed_w = [self.fixed_weights[n] for n in fixed_terms]
        self.register_buffer("_fixed_w", torch.tensor(fixed_w), persistent=False)
        self.register_buffer("_mu", torch.tensor([self.mu[n] for n in stage_terms]), persistent=False)
        self._progress_col = idx[stage_progress_term] if stage_progress_term else -1
        # Episode-end stages counted since the last pop_stage_histogram() (for logging).
        self.register_buffer("stage_histogram", torch.zeros(self.n_stages, dtype=torch.long))

    # -- hooks for the schedules ------------------------------------------------------
    def _coefficients(self, stage: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(a, c)`` broadcastable to ``[*B, A, J]`` for stage ``[*B, A]``."""
        raise NotImplementedError

    def _episodes_ended(self, final: torch.Tensor, ended: torch.Tensor) -> None:
        """Called at every step with the episode-final stage ``[*B, A]`` and its mask."""

    # -- data -------------------------------------------------------------------------
    def _read(self, next_td: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        terms = _get(next_td, self.terms_key, "step output")
        if terms.shape[-1] != len(self.term_names):
            raise ValueError(
                f"{self.terms_key!r} has {terms.shape[-1]} terms in its last dim, the "
                f"schedule is configured with {len(self.term_names)}: {self.term_names}"
            )
        n_agents = _check_agent_shape(self.terms_key, terms.shape, next_td.batch_size, terms.shape[-1:])
        stage = _get(next_td, self.stage_key, "step output")
        _check_agent_shape(self.stage_key, stage.shape, next_td.batch_size, (1,), n_agents)
        return terms, stage.reshape(terms.shape[:-1]).long()

    def _reward(self, terms: torch.Tensor, stage: torch.Tensor) -> torch.Tensor:
        if self._progress_col >= 0:
            terms = terms.clone()
            terms[..., self._progress_col] = stage.to(terms.dtype)
        terms = terms * (stage.unsqueeze(-1) >= self._gate).to(terms.dtype)
        a, c = self._coefficients(stage)
        staged = (a * terms[..., self._stage_idx] + c).sum(-1)
        fixed = (self._fixed_w.to(terms.dtype) * terms[..., self._fixed_idx]).sum(-1)
        return (fixed + staged).unsqueeze(-1)

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        terms, stage = self._read(next_tensordict)
        final = _get(next_tensordict, self.episode_stage_key, "step output")
        _check_agent_shape(self.episode_stage_key, final.shape, next_tensordict.batch_size, (1,), stage.shape[-1])
        final = final.reshape(stage.shape).long()
        self._before_reward(stage)
        next_tensordict.set(self.reward_key, self._reward(terms, stage))
        ended = final >= 0
        self.stage_histogram += torch.bincount(final[ended], minlength=self.n_stages).to(
            self.stage_histogram.device
        )
        self._episodes_ended(final, ended)
        return next_tensordict

    def _before_reward(self, stage: torch.Tensor) -> None:
        """Lazily sized state is created here (first step or reset)."""

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """One env-free step: ``tensordict`` holds t and its ``"next"`` entry."""
        self._refuse_replay_buffer()
        tensordict.set("next", self._step(tensordict, _get(tensordict, "next", "input")))
        return tensordict

    def pop_stage_histogram(self) -> torch.Tensor:
        """Counts of episode-final stages since the last call, then zeroes them."""
        out = self.stage_histogram.clone()
        self.stage_histogram.zero_()
        return out

    # -- specs ------------------------------------------------------------------------
    def transform_reward_spec(self, reward_spec: Composite) -> Composite:
        if self.reward_key in reward_spec.keys(True, True):
            return reward_spec
        obs = self.parent.full_observation_spec
        terms = obs[self.terms_key]
        if terms.shape[-1] != len(self.term_names):
            raise ValueError(
                f"{self.terms_key!r} spec has {terms.shape[-1]} terms, "
                f"expected {len(self.term_names)}"
            )
        _check_agent_shape(self.terms_key, terms.shape, obs.shape, terms.shape[-1:])
        spec = Unbounded(shape=(*terms.shape[:-1], 1), dtype=terms.dtype, device=terms.device)
        _set_nested(reward_spec, self.reward_key, spec, like=obs)
        return reward_spec


class FixedScales(StageRewardSchedule):
    """``rho_j = mu_j`` always: the plain Table II reward."""

    def _coefficients(self, stage):
        return self._mu, self._mu.new_zeros(())


class _LiuSchedule(StageRewardSchedule):
    _bound_name = ""

    def __init__(self, *, bound: Mapping[str, float], **cfg):
        super().__init__(**cfg)
        _check_names(self._bound_name, bound, self.term_names)  # fixed terms' are ignored
        staged = {n: v for n, v in bound.items() if n in self.mu}
        _check_exact(self._bound_name, staged, self.stage_term_names)
        values = torch.tensor([float(bound[n]) for n in self.stage_term_names])
        if not torch.isfinite(values).all():
            bad = [n for n, v in zip(self.stage_term_names, values) if not torch.isfinite(v)]
            raise ValueError(f"{self._bound_name} must be finite for stage-wise terms: {bad}")
        self.register_buffer("_bound", values, persistent=False)

    def _coefficients(self, stage):
        s, ts = stage.unsqueeze(-1), self._term_stage
        a = self._mu * (ts == s)
        c = self._mu * self._bound * (ts < s)
        return a, c


class LiuMax(_LiuSchedule):
    """Completed stages' terms frozen at ``mu_j * high_j`` (Liu et al., max)."""

    _own_keys = frozenset({"high"})
    _bound_name = "high"

    def __init__(self, *, high: Mapping[str, float], **cfg):
        super().__init__(bound=high, **cfg)


class LiuMin(_LiuSchedule):
    """Completed stages' terms frozen at ``mu_j * low_j`` (Liu et al., min)."""

    _own_keys = frozenset({"low"})
    _bound_name = "low"

    def __init__(self, *, low: Mapping[str, float], **cfg):
        super().__init__(bound=low, **cfg)


class AdaptiveRewardScaling(_LazyBuffers, StageRewardSchedule):
    """The paper's adaptive reward scaling (Eq. 2), per world and per robot.

    At each reset of a slot whose episode ended (``episode_stage >= 0`` was seen) in
    stage lambda: ``rho_j <- min(K rho_j, mu_j)`` for terms of stage lambda and
    ``rho_j <- max(rho_j / K, mu_min)`` for the others; constant within an episode.
    After ``final_after`` consecutive episodes ending in the last stage, the slot enters
    the final stage: ``rho_j = mu_j`` for good. A reset without an ended episode (the
    first reset, or a reset that cuts an episode short) changes nothing.

    Initialisation (our choice, the paper is silent): ``rho_j = mu_j`` for stage-0
    terms, ``mu_min`` for the others: where episodes that keep ending in S0 lead.

    State (``rho`` ``[*B, A, J]`` over :attr:`stage_term_names`, ``final_streak``,
    ``in_final``, ``pending_stage``, ``stage_histogram``) lives in buffers, in the
    ``state_dict``, sized on the first reset (from the stage written before it) or the
    first step. It is per process: each worker of a ``ParallelEnv`` or collector holds
    its own when the transform lives in the worker.

    ``completed_floor`` (ours; 0, the default, is the paper's Eq. 2): terms whose stage
    lies below lambda keep ``rho_j >= completed_floor * mu_j``.
    """

    _own_keys = frozenset({"K", "mu_min", "final_after", "completed_floor"})
    _lazy = ("rho", "final_streak", "in_final", "pending_stage")

    def __init__(self, *, K: float, mu_min: float, final_after: int = 5, completed_floor: float = 0.0, **cfg):
        super().__init__(**cfg)
        if not 0.0 <= completed_floor <= 1.0:
            raise ValueError(f"completed_floor must be in [0, 1], got {completed_floor}")
        if not K > 1:
            raise ValueError(f"K must be > 1, got {K}")
        if not mu_min > 0:
            raise ValueError(f"mu_min must be > 0, got {mu_min}")
        too_small = [n for n, m in self.mu.items() if m < mu_min]
        if too_small:
            raise ValueError(
                f"mu_min={mu_min} exceeds mu_j of {too_small}: rho_j has no valid range"
            )
        if final_after < 1:
            raise ValueError(f"final_after must be >= 1, got {final_after}")
        self.K, self.mu_min, self.final_after = float(K), float(mu_min), int(final_after)
        self.completed_floor = float(completed_floor)
        for name in self._lazy:
            self.register_buffer(name, torch.empty(0))

    @property
    def initialized(self) -> bool:
        return self.rho.ndim >= 2

    def _before_reward(self, stage: torch.Tensor) -> None:
        if not self.initialized:
            slots, dev = stage.shape, stage.device
            rho = torch.where(self._term_stage == 0, self._mu, self.mu_min)
            self.rho = rho.to(dev).expand(*slots, -1).clone()
            self.final_streak = torch.zeros(slots, dtype=torch.long, device=dev)
            self.in_final = torch.zeros(slots, dtype=torch.bool, device=dev)
            self.pending_stage = torch.full(slots, -1, dtype=torch.long, device=dev)
        elif self.rho.shape[:-1] != stage.shape:
            raise ValueError(
                f"batch of {self.stage_key!r} {tuple(stage.shape)} differs from the "
                f"curriculum state {tuple(self.rho.shape[:-1])}"
            )

    def _coefficients(self, stage):
        return self.rho, self.rho.new_zeros(())

    def _episodes_ended(self, final, ended):
        self.pending_stage = torch.where(ended, final, self.pending_stage)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        if not self.initialized:  # no step yet, so no episode has ended: only allocate
            stage = tensordict_reset.get(self.stage_key, None)
            if stage is not None:
                n_agents = _check_agent_shape(self.stage_key, stage.shape, tensordict_reset.batch_size, (1,))
                _check_group_batch(tensordict_reset, self.stage_key, n_agents)
                self._before_reward(stage.reshape(stage.shape[:-1]))
            return tensordict_reset
        pending = self.pending_stage
        reset = _slot_reset_mask(tensordict, self.reset_keys, pending.shape, pending.device)
        self.update(reset)
        return tensordict_reset

    def update(self, reset: torch.Tensor) -> None:
        """Apply Eq. 2 to the slots in ``reset`` (bool ``[*B, A]``) whose episode ended."""
        lam = self.pending_stage
        upd = reset & (lam >= 0) & ~self.in_final
        in_j = self._term_stage == lam.unsqueeze(-1)
        mu = self._mu.to(self.rho)
        up = torch.minimum(self.rho * self.K, mu)
        down = torch.clamp(self.rho / self.K, min=self.mu_min)
        if self.completed_floor > 0:  # not in Eq. 2: terms of stages below lambda keep a share of mu
            done = self._term_stage < lam.unsqueeze(-1)
            down = torch.where(done, torch.maximum(down, self.completed_floor * mu), down)
        new = torch.where(in_j, up, down)
        self.rho = torch.where(upd.unsqueeze(-1), new, self.rho)
        last = self.n_stages - 1
        streak = torch.where(lam == last, self.final_streak + 1, 0)
        self.final_streak = torch.where(upd, streak, self.final_streak)
        self.in_final = self.in_final | (upd & (self.final_streak >= self.final_after))
        self.rho = torch.where(self.in_final.unsqueeze(-1), mu, self.rho)
        self.pending_stage = torch.where(reset, -1, self.pending_stage)

    def rho_by_term(self) -> dict[str, float]:
        """Mean ``rho_j`` over worlds and robots, by term name (for logging)."""
        if not self.initialized:
            return {}
        mean = self.rho.reshape(-1, self.rho.shape[-1]).mean(0)
        return {n: float(v) for n, v in zip(self.stage_term_names, mean)}

    def enter_final(self) -> None:
        """Put every slot in the final stage (``rho_j = mu_j`` for good), as if each had
        ended ``final_after`` episodes in the last stage: for a run that continues a policy
        which already reaches it, on new worlds."""
        if not self.initialized:
            raise RuntimeError("enter_final: the curriculum state is allocated at the env's first reset")
        self.in_final = torch.ones_like(self.in_final)
        self.final_streak = torch.full_like(self.final_streak, self.final_after)
        self.rho = self._mu.to(self.rho).expand_as(self.rho).clone()


SCHEDULES: dict[str, type[StageRewardSchedule]] = {
    "dynamic": AdaptiveRewardScaling,
    "fixed": FixedScales,
    "liu_max": LiuMax,
    "liu_min": LiuMin,
}


def make_reward_schedule(schedule: str, **cfg) -> StageRewardSchedule:
    """Build a schedule by name (``"dynamic"``, ``"fixed"``, ``"liu_max"``, ``"liu_min"``).

    One config serves all: keys that belong only to other schedules (``K``, ``mu_min``,
    ``final_after``, ``low``, ``high``) are dropped; any other unknown key is an error.
    """
    if schedule not in SCHEDULES:
        raise ValueError(f"unknown reward schedule {schedule!r}; choose from {sorted(SCHEDULES)}")
    cls = SCHEDULES[schedule]
    others = frozenset().union(*(c._own_keys for c in SCHEDULES.values())) - cls._own_keys
    return cls(**{k: v for k, v in cfg.items() if k not in others})
