"""``StageTransition``: the stage transition graph as a stateless TorchRL transform.

The stage lives in the tensordict, not in the transform: ``_step`` reads the stage at
time t from the input and writes the stage at t+1 into ``"next"``. Like
``TensorDictPrimer``, the stage is declared in both the observation and the state spec,
so that batched envs (``SerialEnv``/``ParallelEnv``) pass it back to their workers and
collectors carry it across steps; no buffer has to match a batch size.
"""
from __future__ import annotations

from typing import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey, unravel_key
from torchrl.data import Bounded, Categorical, Composite, OneHot
from torchrl.envs.transforms import Transform
from torchrl.envs.transforms.utils import _get_reset

from ._graph import StageGraph

from ._checks import _check_agent_shape, _check_group_batch, _ClonesOwnBuffers, _EnvOnly, _fmt, _get

__all__ = ["StageTransition"]


def _slot_reset_mask(
    td: TensorDictBase,
    reset_keys: Sequence[NestedKey],
    slot_shape: torch.Size,
    device: torch.device,
) -> torch.Tensor:
    """Bool ``[*B, A]``: which (world, agent) slots a reset touches.

    Reset keys may sit at the root (``"_reset"`` ``[*B, 1]``) or in the agent group
    (``("agents", "_reset")`` ``[*B, A, 1]``); no reset key at all means a full reset.
    """
    keys = [k for k in reset_keys if td.get(k, None) is not None]
    if not keys:
        return torch.ones(slot_shape, dtype=torch.bool, device=device)
    mask = torch.zeros(slot_shape, dtype=torch.bool, device=device)
    for key in keys:
        m = _get_reset(key, td).to(device)
        m = m.reshape(*m.shape, *([1] * (len(slot_shape) - m.ndim)))
        mask |= m.expand(slot_shape)
    return mask


def _done_per_slot(done: torch.Tensor, slot_shape: torch.Size) -> torch.Tensor:
    """Team done ``[*B, 1]`` or per-agent done ``[*B, A, 1]`` -> bool ``[*B, A]``."""
    batch = slot_shape[:-1]
    return done.reshape(*batch, -1).bool().expand(slot_shape)


class _ResetKeysMixin:
    """Reset keys: given, else the parent env's, else the root ``"_reset"``."""

    def _init_reset_keys(self, reset_keys: Sequence[NestedKey] | None) -> None:
        if reset_keys is not None:
            reset_keys = [unravel_key(k) for k in reset_keys]
        self._given_reset_keys = reset_keys

    @property
    def reset_keys(self) -> list[NestedKey]:
        if self._given_reset_keys is not None:
            return self._given_reset_keys
        parent = self.parent
        return list(parent.reset_keys) if parent is not None else ["_reset"]


class StageTransition(_ClonesOwnBuffers, _ResetKeysMixin, _EnvOnly, Transform):
    """Advances each robot's stage along a :class:`~pnp.task.stage_graph.StageGraph`.

    Reads ``conditions_key`` (bool ``[*B, A, C]``, columns in ``graph.conditions``
    order) at t+1 and the stage at t; writes the stage at t+1. Keys written:

    * ``stage_key``: int64 ``[*B, A, 1]`` (trailing 1 as for rewards and dones);
      ``0`` after reset. Observation and state spec.
    * ``episode_stage_key``: int64 ``[*B, A, 1]``, the stage at the step where
      ``done_key`` is true (the episode's final stage, before the reset), ``-1`` at every
      other step. The reward schedules and loggers read it.
    * ``one_hot_key`` (optional): float ``[*B, A, n_stages]``, for the teacher's
      observation.

    ``episode_stage`` picks the stage lambda(e) reported at the episode's end: ``"final"``
    (default, the stage it ends in) or ``"peak"`` (the highest stage reached in it, kept
    per slot under ``peak_key`` as state). The paper says "the final stage reached"; with
    the backward edges S2->S0 and S1->S0 the two readings differ: under ``"final"`` a
    robot that grasps, drops and re-grasps ends in S0, S1 or S2 by chance.

    Place it after any transform that changes ``done`` (e.g. ``StepCounter``).
    ``transform(td)`` outside an env runs one step on a td holding t and ``"next"``.

    Per-robot entries have shape ``[*B, A, ...]`` (``B`` the env batch): a group of another
    batch is a ``ValueError`` naming the key. Not for replay buffers: the stage advances
    one step at a time in each env world, and a sampled batch has no world identity, so
    ``forward`` refuses when it finds itself in one (eval mode, no env); stages are
    computed in the env and stored with the data.
    """

    _needs_env = "it advances each env world's stage one step at a time"
    _instead = "Compute the stages in the env (TransformedEnv(env, StageTransition(...))) and store them."

    def __init__(
        self,
        graph: StageGraph,
        conditions_key: NestedKey = ("agents", "stage_conditions"),
        stage_key: NestedKey = ("agents", "stage"),
        episode_stage_key: NestedKey = ("agents", "episode_stage"),
        one_hot_key: NestedKey | None = None,
        done_key: NestedKey = "done",
        reset_keys: Sequence[NestedKey] | None = None,
        episode_stage: str = "final",
        peak_key: NestedKey = ("agents", "stage_peak"),
    ):
        if episode_stage not in ("final", "peak"):
            raise ValueError(f"episode_stage must be 'final' or 'peak', got {episode_stage!r}")
        self.graph, self.episode_stage = graph, episode_stage
        self.peak_key = unravel_key(peak_key) if episode_stage == "peak" else None
        self.conditions_key = unravel_key(conditions_key)
        self.stage_key = unravel_key(stage_key)
        self.episode_stage_key = unravel_key(episode_stage_key)
        self.one_hot_key = None if one_hot_key is None else unravel_key(one_hot_key)
        self.done_key = unravel_key(done_key)
        out_keys = [self.stage_key, self.episode_stage_key]
        if self.peak_key is not None:
            out_keys.append(self.peak_key)
        if self.one_hot_key is not None:
            out_keys.append(self.one_hot_key)
        super().__init__(in_keys=[self.conditions_key], out_keys=out_keys)
        self._init_reset_keys(reset_keys)

    # -- data -------------------------------------------------------------------------
    def _write(self, td: TensorDictBase, stage: torch.Tensor, final: torch.Tensor,
               peak: torch.Tensor | None = None) -> None:
        td.set(self.stage_key, stage.unsqueeze(-1))
        td.set(self.episode_stage_key, final.unsqueeze(-1))
        if self.peak_key is not None:
            td.set(self.peak_key, peak.unsqueeze(-1))
        if self.one_hot_key is not None:
            one_hot = torch.nn.functional.one_hot(stage, self.graph.n_stages)
            td.set(self.one_hot_key, one_hot.to(torch.get_default_dtype()))

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        cond = _get(next_tensordict, self.conditions_key, "step output")
        if cond.shape[-1] != len(self.graph.conditions):
            raise ValueError(
                f"{self.conditions_key!r} has {cond.shape[-1]} columns, the graph has "
                f"{len(self.graph.conditions)} conditions {self.graph.conditions}"
            )
        n_agents = _check_agent_shape(self.conditions_key, cond.shape, next_tensordict.batch_size, cond.shape[-1:])
        stage = _get(tensordict, self.stage_key, "step input (reset the env first?)")
        _check_agent_shape(self.stage_key, stage.shape, tensordict.batch_size, (1,), n_agents)
        stage = stage.reshape(cond.shape[:-1])
        new = self.graph.next_stage(stage, cond)
        done = _done_per_slot(_get(next_tensordict, self.done_key, "step output"), new.shape)
        peak = None
        if self.peak_key is not None:
            peak = torch.maximum(_get(tensordict, self.peak_key, "step input").reshape(new.shape), new)
        self._write(next_tensordict, new, torch.where(done, new if peak is None else peak, -1), peak)
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        # Slot shape from the conditions if the env emits them at reset, else from the
        # previous stage; worlds not reset keep their stage.
        prev = tensordict.get(self.stage_key, None)
        cond = tensordict_reset.get(self.conditions_key, None)
        if cond is not None:
            n_agents = _check_agent_shape(self.conditions_key, cond.shape, tensordict_reset.batch_size, cond.shape[-1:])
            _check_group_batch(tensordict_reset, self.conditions_key, n_agents)
        if prev is not None:
            _check_agent_shape(self.stage_key, prev.shape, tensordict.batch_size, (1,))
        like = cond if cond is not None else prev
        if like is not None:
            slots, device = like.shape[:-1], like.device
        else:
            slots, device = self._slot_shape_from_spec(tensordict_reset), tensordict_reset.device
        reset = _slot_reset_mask(tensordict, self.reset_keys, slots, device)
        # A partial reset given the reset keys alone (TorchRL's own step_and_maybe_reset does so)
        # writes zeros for the other slots too: TorchRL then merges the output into the carried
        # tensordict by the mask, and pads every entry it lacks with 0 (docs/guide/own_env.md).
        stage = torch.zeros(slots, dtype=torch.long, device=device)
        if prev is not None:
            stage = torch.where(reset, stage, prev.reshape(slots))
        peak = None
        if self.peak_key is not None:
            prev_peak = tensordict.get(self.peak_key, None)
            peak = stage if prev_peak is None else torch.where(reset, stage, prev_peak.reshape(slots))
        self._write(tensordict_reset, stage, torch.full_like(stage, -1), peak)
        return tensordict_reset

    def _slot_shape_from_spec(self, td: TensorDictBase) -> torch.Size:
        parent = self.parent
        if parent is None:
            raise KeyError(
                f"cannot size the stage: neither {self.conditions_key!r} in the reset "
                f"output nor {self.stage_key!r} in the input, and no parent env"
            )
        spec = parent.full_observation_spec
        if self.conditions_key not in spec.keys(True, True):
            present = ", ".join(sorted(_fmt(k) for k in spec.keys(True, True)))
            raise KeyError(
                f"StageTransition reads {_fmt(self.conditions_key)} (bool [*B, A, C], a group of batch [*B, A]); "
                f"the env's observation spec has: {present}. Emit the per-robot entries in that group "
                f"(at reset too), or pass conditions_key= the key the env uses"
            )
        return spec[self.conditions_key].shape[:-1]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """One env-free step: ``tensordict`` holds t and its ``"next"`` entry."""
        self._refuse_replay_buffer()
        next_td = _get(tensordict, "next", "input")
        tensordict.set("next", self._step(tensordict, next_td))
        return tensordict

    # -- specs ------------------------------------------------------------------------
    def _new_specs(self, like: Composite) -> dict:
        cond_spec = like[self.conditions_key]
        if cond_spec.shape[-1] != len(self.graph.conditions):
            raise ValueError(
                f"{self.conditions_key!r} spec has {cond_spec.shape[-1]} columns, the "
                f"graph has {len(self.graph.conditions)} conditions"
            )
        _check_agent_shape(self.conditions_key, cond_spec.shape, like.shape, cond_spec.shape[-1:])
        slots, n, dev = cond_spec.shape[:-1], self.graph.n_stages, cond_spec.device
        specs = {
            self.stage_key: Categorical(n, shape=(*slots, 1), dtype=torch.long, device=dev),
            self.episode_stage_key: Bounded(
                -1, n - 1, shape=(*slots, 1), dtype=torch.long, device=dev
            ),
        }
        if self.peak_key is not None:
            specs[self.peak_key] = Categorical(n, shape=(*slots, 1), dtype=torch.long, device=dev)
        if self.one_hot_key is not None:
            specs[self.one_hot_key] = OneHot(
                n, shape=(*slots, n), dtype=torch.get_default_dtype(), device=dev
            )
        return specs

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        for key, spec in self._new_specs(observation_spec).items():
            _set_nested(observation_spec, key, spec, like=observation_spec)
        return observation_spec

    def transform_input_spec(self, input_spec: Composite) -> Composite:
        # The stage at t is an input of step: declare it as state (see module doc).
        obs = self.parent.output_spec["full_observation_spec"]
        state = input_spec["full_state_spec"]
        if state is None:
            state = Composite(shape=input_spec.shape, device=input_spec.device)
        new = self._new_specs(obs)
        for key in (self.stage_key, self.peak_key):
            if key is not None:
                _set_nested(state, key, new[key], like=obs)
        input_spec["full_state_spec"] = state
        return input_spec


def _set_nested(root: Composite, key: NestedKey, spec, like: Composite) -> None:
    """``root[key] = spec``, creating missing groups with the batch shape ``like`` has."""
    key = (key,) if isinstance(key, str) else key
    for i in range(1, len(key)):
        prefix = key[:i]
        if prefix not in root.keys(True):
            node_shape = like[prefix].shape if prefix in like.keys(True) else spec.shape[:-1]
            root[prefix] = Composite(shape=node_shape, device=spec.device)
    root[key] = spec
