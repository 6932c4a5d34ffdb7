"""``ObservationNoise``: Gaussian noise and held-value dropouts on observation columns.

Knows nothing of the task: the observation's column layout is configuration. The
dropout state (last value seen, steps left to hold) is per (world, agent) slot, in
buffers sized at the first call, so it lands in the ``state_dict``.
"""
from __future__ import annotations

import itertools
import math
from collections.abc import Mapping

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey, unravel_key
from torchrl.data import Composite
from torchrl.envs.transforms import Transform

from ._checks import _check_agent_shape, _ClonesOwnBuffers, _EnvOnly, _fmt, _get, _LazyBuffers
from ._stage import _ResetKeysMixin, _set_nested, _slot_reset_mask

__all__ = ["ObservationNoise"]


def _columns(name: str, cols) -> tuple[int, int]:
    if isinstance(cols, slice):
        if cols.step not in (None, 1):
            raise ValueError(f"fields[{name!r}]: slice step must be 1, got {cols}")
        cols = (cols.start or 0, cols.stop)
    start, stop = cols
    if not (isinstance(start, int) and isinstance(stop, int) and 0 <= start < stop):
        raise ValueError(f"fields[{name!r}]: columns must be [start, stop) with 0 <= start < stop, got {cols}")
    return start, stop


class ObservationNoise(_ClonesOwnBuffers, _LazyBuffers, _ResetKeysMixin, _EnvOnly, Transform):
    """Per-field Gaussian noise and mocap-like dropouts on an observation's columns.

    Noise model: ``fields`` names column ranges ``[start, stop)`` of the observation's
    last dim, each with a std ``sigma``; every step (and at reset) each named column gets
    ``N(0, sigma^2)`` noise, drawn independently per world, agent and column; columns not
    named are left exactly as they are. A field listed in ``dropouts`` with
    ``(p, min_hold_s, max_hold_s)`` can also drop out: after each step where it was seen,
    with probability ``p`` a dropout starts in that (world, agent) slot and the field's
    columns then hold the last (noisy) value the policy saw for
    ``max(1, round(d / dt))`` steps, ``d ~ U[min_hold_s, max_hold_s]``, then move again.

    For a pick-and-place-like layout ``[joints(7) | ee_pos(3) | obj_pos(3) | goal(3)]``::

        ObservationNoise(
            fields={"joints": ((0, 7), 0.01), "ee_pos": (slice(7, 10), 0.005),
                    "obj_pos": ((10, 13), 0.01)},          # goal left clean
            dropouts={"obj_pos": (0.02, 0.1, 0.5)},        # 2 %/step, held 0.1-0.5 s
            dt=0.1, generator_seed=0,
        )

    Reset: the reset slots' dropouts are cleared and their reset observation is seen
    fresh (noisy, never held); a dropout may start right after it. Slots not reset keep
    their state. ``in_key`` in a group (``("agents", "observation")``) must have shape
    ``[*B, A, D]`` (``B`` the env batch), a root key ``[*B, D]``. ``out_key=None`` writes in
    place, else the noisy copy goes to ``out_key`` and the spec is copied there. With
    ``generator_seed`` the transform owns a CPU ``torch.Generator`` (noise drawn on CPU,
    then moved) whose state is in the ``state_dict``; else the global RNG. Not for replay
    buffers: the dropouts are per env world.
    """

    _needs_env = "its dropouts hold values per env world and agent, one step at a time"
    _instead = "Add the noise in the env (TransformedEnv(env, ObservationNoise(...))) and store it."
    _lazy = ("held", "hold_left")

    def __init__(
        self,
        fields: Mapping[str, tuple[slice | tuple[int, int], float]],
        in_key: NestedKey = ("agents", "observation"),
        out_key: NestedKey | None = None,
        dropouts: Mapping[str, tuple[float, float, float]] | None = None,
        dt: float = 0.1,
        generator_seed: int | None = None,
    ):
        self.in_key = unravel_key(in_key)
        self.out_key = self.in_key if out_key is None else unravel_key(out_key)
        super().__init__(in_keys=[self.in_key], out_keys=[self.out_key])
        self._init_reset_keys(None)
        if not dt > 0:
            raise ValueError(f"dt must be > 0, got {dt}")
        self.fields: dict[str, tuple[int, int]] = {}
        self.sigma: dict[str, float] = {}
        for name, (cols, std) in fields.items():
            self.fields[name] = _columns(name, cols)
            if not (math.isfinite(std) and std >= 0):
                raise ValueError(f"fields[{name!r}]: std must be finite and >= 0, got {std}")
            self.sigma[name] = float(std)
        spans = sorted((c, n) for n, c in self.fields.items())
        for (a, name_a), (b, name_b) in itertools.pairwise(spans):
            if b[0] < a[1]:
                raise ValueError(f"fields {name_a!r} {list(a)} and {name_b!r} {list(b)} overlap")
        self.dropouts: dict[str, tuple[float, int, int]] = {}
        for name, (p, lo, hi) in (dropouts or {}).items():
            if name not in self.fields:
                raise ValueError(f"dropouts[{name!r}]: unknown field; fields are {tuple(self.fields)}")
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"dropouts[{name!r}]: probability must be in [0, 1], got {p}")
            if not 0.0 <= lo <= hi:
                raise ValueError(f"dropouts[{name!r}]: need 0 <= min_hold_s <= max_hold_s, got ({lo}, {hi})")
            self.dropouts[name] = (float(p), float(lo), float(hi))
        self.dt = float(dt)
        self.n_cols = max((c[1] for c in self.fields.values()), default=0)  # needed width
        drop = list(self.dropouts)
        # Lookup tensors (not state), over the first n_cols columns.
        sigma = torch.zeros(self.n_cols)
        drop_cols = torch.zeros(len(drop), self.n_cols, dtype=torch.bool)
        for name, (start, stop) in self.fields.items():
            sigma[start:stop] = self.sigma[name]
        for k, name in enumerate(drop):
            start, stop = self.fields[name]
            drop_cols[k, start:stop] = True
        self.register_buffer("_sigma", sigma, persistent=False)
        self.register_buffer("_drop_cols", drop_cols, persistent=False)
        spec = torch.tensor([self.dropouts[n] for n in drop]).reshape(len(drop), 3)
        self.register_buffer("_drop_p", spec[:, 0].contiguous(), persistent=False)
        self.register_buffer("_drop_lo", spec[:, 1].contiguous(), persistent=False)
        self.register_buffer("_drop_hi", spec[:, 2].contiguous(), persistent=False)
        # State: last observation the policy saw, steps left in each field's dropout.
        for name in self._lazy:
            self.register_buffer(name, torch.empty(0))
        self.generator = None
        if generator_seed is not None:
            self.generator = torch.Generator().manual_seed(int(generator_seed))

    # -- checks -----------------------------------------------------------------------
    def _check_width(self, width: int, where: str) -> None:
        out = [f"{n!r} {list(c)}" for n, c in self.fields.items() if c[1] > width]
        if out:
            raise ValueError(
                f"field(s) {', '.join(out)} outside {_fmt(self.in_key)} ({where} has {width} columns)"
            )

    def _check_shape(self, shape, batch, where: str) -> None:
        if isinstance(self.in_key, tuple) and len(self.in_key) > 1:  # per-agent group
            _check_agent_shape(self.in_key, shape, batch, shape[-1:])
        self._check_width(shape[-1], where)

    # -- noise ------------------------------------------------------------------------
    def _rand(self, fn, shape, like: torch.Tensor) -> torch.Tensor:
        if self.generator is None:
            return fn(shape, device=like.device, dtype=like.dtype)
        return fn(shape, generator=self.generator, dtype=like.dtype).to(like.device)

    def _noisy(self, td: TensorDictBase, update: torch.Tensor | None) -> TensorDictBase:
        """Noise (and dropouts) on ``td``; state updated in the slots of ``update``."""
        obs = _get(td, self.in_key, "observation")
        self._check_shape(obs.shape, td.batch_size, "the data")
        slots, width = obs.shape[:-1], obs.shape[-1]
        sigma = torch.nn.functional.pad(self._sigma.to(obs), (0, width - self.n_cols))
        out = obs + sigma * self._rand(torch.randn, obs.shape, obs)
        if self.dropouts:
            self._init_state(obs)
            frozen = self.hold_left > 0  # [*slots, K]
            cols = (frozen.unsqueeze(-1) & self._drop_cols).any(-2)
            cols = torch.nn.functional.pad(cols, (0, width - self.n_cols))
            out = torch.where(cols, self.held, out)
            # A dropout may start after a step where the field was seen.
            k = len(self.dropouts)
            start = self._rand(torch.rand, (*slots, k), obs) < self._drop_p.to(obs)
            u = self._rand(torch.rand, (*slots, k), self._drop_lo)
            d = self._drop_lo + (self._drop_hi - self._drop_lo) * u
            steps = torch.round(d / self.dt).clamp(min=1).long()
            left = torch.where(frozen, self.hold_left - 1, torch.where(start, steps, 0))
            keep = torch.ones_like(frozen[..., 0]) if update is None else update
            self.hold_left = torch.where(keep.unsqueeze(-1), left, self.hold_left)
            self.held = torch.where(keep.unsqueeze(-1), out, self.held)
        td.set(self.out_key, out)
        return td

    def _init_state(self, obs: torch.Tensor) -> None:
        slots = obs.shape[:-1]
        if self.held.shape == (0,):  # not sized yet
            self.held = obs.detach().clone()
            self.hold_left = torch.zeros(*slots, len(self.dropouts), dtype=torch.long, device=obs.device)
        elif self.held.shape != obs.shape:
            raise ValueError(
                f"{_fmt(self.in_key)} has shape {list(obs.shape)}, the dropout state was "
                f"sized for {list(self.held.shape)}"
            )

    # -- TorchRL hooks ----------------------------------------------------------------
    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        self._refuse_replay_buffer()
        return self._noisy(next_tensordict, None)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Env-free: one step of noise on ``tensordict``'s ``in_key`` (all slots)."""
        return self._call(tensordict)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        obs = _get(tensordict_reset, self.in_key, "reset output")
        self._check_shape(obs.shape, tensordict_reset.batch_size, "the reset output")
        reset = _slot_reset_mask(tensordict, self.reset_keys, obs.shape[:-1], obs.device)
        if self.dropouts:
            self._init_state(obs)
            self.hold_left = torch.where(reset.unsqueeze(-1), 0, self.hold_left)
        return self._noisy(tensordict_reset, reset)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        spec = observation_spec[self.in_key]
        self._check_shape(spec.shape, observation_spec.shape, "the observation spec")
        if self.out_key != self.in_key:
            _set_nested(observation_spec, self.out_key, spec.clone(), like=observation_spec)
        return observation_spec

    # -- state ------------------------------------------------------------------------
    def get_extra_state(self):
        return None if self.generator is None else {"generator": self.generator.get_state()}

    def set_extra_state(self, state) -> None:
        if state is not None:  # a seeded run resumes seeded, whatever this one was built with
            self.generator = self.generator or torch.Generator()
            self.generator.set_state(state["generator"])

