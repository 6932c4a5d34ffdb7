"""``ColumnHistory``: the last few values of some observation columns, appended to it.

Knows nothing of the task: the observation's column layout is configuration. The history
is per (world, agent) slot, in a buffer sized at the first call, so it lands in the
``state_dict``.
"""
from __future__ import annotations

import itertools
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey, unravel_key
from torchrl.data import Composite, Unbounded
from torchrl.envs.transforms import Transform

from ._checks import _check_agent_shape, _ClonesOwnBuffers, _EnvOnly, _fmt, _get, _LazyBuffers
from ._stage import _ResetKeysMixin, _set_nested, _slot_reset_mask

__all__ = ["ColumnHistory"]


def _span(what: str, cols) -> tuple[int, int]:
    try:
        start, stop = cols
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be a (start, stop) pair, got {cols!r}") from None
    if not (isinstance(start, int) and isinstance(stop, int) and 0 <= start < stop):
        raise ValueError(f"{what} must be [start, stop) with 0 <= start < stop, got {cols!r}")
    return start, stop


class ColumnHistory(_ClonesOwnBuffers, _LazyBuffers, _ResetKeysMixin, _EnvOnly, Transform):
    """Appends the last ``length`` values of observation columns ``[start, stop)``.

    For a student that must infer its end-effector pose from the history of its arm's
    joints instead of reading it: keep the joint columns' history and drop the pose
    columns. With our ego block (configuration, not known here), where columns 3-8 are
    ``arm_q`` and 15-19 the EE position and yaw::

        ColumnHistory(columns=(3, 9), length=4, drop=[(15, 20)])

    Output (``out_key``, default in place into ``in_key``): the observation with the
    ``drop`` column ranges removed, then the flattened history, most recent first:
    ``[obs without drop | cols(t) | cols(t-1) | ... | cols(t-length+1)]``, i.e.
    ``D - dropped + length * (stop - start)`` columns. The history includes the current
    step's columns (as frame stacking does), read before the drop. Place it after any
    transform that edits those columns (e.g. ``ObservationNoise``): the history is of what
    the policy saw.

    Reset: the reset slots' history is filled with the reset observation's columns, so
    the first observation of an episode sees a constant history; slots not reset keep
    theirs (and their reset output shows it unchanged). ``in_key`` in a group
    (``("agents", "observation")``) must have shape ``[*B, A, D]`` (``B`` the env batch), a
    root key ``[*B, D]``. Not for replay buffers: the history is per env world and step.
    """

    _needs_env = "its history is per env world and agent, one step at a time"
    _instead = "Stack the history in the env (TransformedEnv(env, ColumnHistory(...))) and store it."
    _lazy = ("history",)

    def __init__(
        self,
        columns: tuple[int, int],
        length: int,
        in_key: NestedKey = ("agents", "observation"),
        out_key: NestedKey | None = None,
        drop: Sequence[tuple[int, int]] = (),
    ):
        self.in_key = unravel_key(in_key)
        self.out_key = self.in_key if out_key is None else unravel_key(out_key)
        super().__init__(in_keys=[self.in_key], out_keys=[self.out_key])
        self._init_reset_keys(None)
        self.columns = _span("columns", columns)
        if not (isinstance(length, int) and length >= 1):
            raise ValueError(f"length must be an int >= 1, got {length!r}")
        self.length = length
        self.drop = sorted(_span(f"drop[{i}]", d) for i, d in enumerate(drop))
        for a, b in itertools.pairwise(self.drop):
            if b[0] < a[1]:
                raise ValueError(f"drop ranges {list(a)} and {list(b)} overlap")
        self.n_cols = max([self.columns[1], *(d[1] for d in self.drop)])  # needed width
        dropped = torch.zeros(self.n_cols, dtype=torch.bool)
        for start, stop in self.drop:
            dropped[start:stop] = True
        self.register_buffer("_dropped", dropped, persistent=False)  # lookup, not state
        for name in self._lazy:
            self.register_buffer(name, torch.empty(0))

    @property
    def k(self) -> int:
        return self.columns[1] - self.columns[0]

    def out_width(self, width: int) -> int:
        """Columns written for an observation of ``width`` columns."""
        return width - int(self._dropped.sum()) + self.length * self.k

    # -- checks -----------------------------------------------------------------------
    def _check_shape(self, shape, batch, where: str) -> None:
        if isinstance(self.in_key, tuple) and len(self.in_key) > 1:  # per-agent group
            _check_agent_shape(self.in_key, shape, batch, shape[-1:])
        width = shape[-1]
        out = [f"{what} {list(c)}" for what, c in [("columns", self.columns), *(("drop", d) for d in self.drop)]
               if c[1] > width]
        if out:
            raise ValueError(f"{', '.join(out)} outside {_fmt(self.in_key)} ({where} has {width} columns)")

    def _init_state(self, obs: torch.Tensor) -> None:
        shape = (*obs.shape[:-1], self.length, self.k)
        if self.history.shape == (0,):  # not sized yet
            cols = obs[..., self.columns[0] : self.columns[1]].detach()
            self.history = cols.unsqueeze(-2).expand(shape).clone()
        elif self.history.shape != shape:
            raise ValueError(
                f"{_fmt(self.in_key)} has shape {list(obs.shape)}, the history was sized for "
                f"{list(self.history.shape)} ([*slots, length, k])"
            )

    # -- history ----------------------------------------------------------------------
    def _write(self, td: TensorDictBase, obs: torch.Tensor) -> TensorDictBase:
        keep = ~torch.nn.functional.pad(self._dropped.to(obs.device), (0, obs.shape[-1] - self.n_cols))
        td.set(self.out_key, torch.cat([obs[..., keep], self.history.flatten(-2).to(obs)], dim=-1))
        return td

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        self._refuse_replay_buffer()
        obs = _get(next_tensordict, self.in_key, "observation")
        self._check_shape(obs.shape, next_tensordict.batch_size, "the data")
        self._init_state(obs)
        cols = obs[..., self.columns[0] : self.columns[1]].detach().unsqueeze(-2)
        self.history = torch.cat([cols.to(self.history), self.history[..., :-1, :]], dim=-2)
        return self._write(next_tensordict, obs)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Env-free: one step of history on ``tensordict``'s ``in_key`` (all slots)."""
        return self._call(tensordict)

    # -- TorchRL hooks ----------------------------------------------------------------
    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        obs = _get(tensordict_reset, self.in_key, "reset output")
        self._check_shape(obs.shape, tensordict_reset.batch_size, "the reset output")
        self._init_state(obs)
        reset = _slot_reset_mask(tensordict, self.reset_keys, obs.shape[:-1], obs.device)
        cols = obs[..., self.columns[0] : self.columns[1]].detach().unsqueeze(-2).to(self.history)
        self.history = torch.where(reset[..., None, None].to(self.history.device), cols, self.history)
        return self._write(tensordict_reset, obs)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        spec = observation_spec[self.in_key]
        self._check_shape(spec.shape, observation_spec.shape, "the observation spec")
        shape = (*spec.shape[:-1], self.out_width(spec.shape[-1]))
        new = Unbounded(shape=shape, dtype=spec.dtype, device=spec.device)
        _set_nested(observation_spec, self.out_key, new, like=observation_spec)
        return observation_spec

    # -- state ------------------------------------------------------------------------
