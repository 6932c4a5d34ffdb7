"""Input checks shared by the curriculum transforms, with errors that name the bad value."""
from __future__ import annotations

from typing import Mapping, Sequence

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey


def _get(td: TensorDictBase, key: NestedKey, where: str) -> torch.Tensor:
    """``td.get(key)`` with an error that says what is there instead."""
    value = td.get(key, None)
    if value is None:
        present = ", ".join(sorted(_fmt(k) for k in td.keys(True, True)))
        raise KeyError(f"{_fmt(key)} not found in the {where} tensordict; keys present: {present}")
    return value


def _fmt(key: NestedKey) -> str:
    """``("agents", "stage")`` -> ``agents.stage`` (KeyError messages escape quotes)."""
    return key if isinstance(key, str) else ".".join(key)


def _check_agent_shape(
    key: NestedKey,
    shape: Sequence[int],
    batch: Sequence[int],
    trailing: Sequence[int],
    n_agents: int | None = None,
) -> int:
    """Checks that an agent entry has shape ``[*B, A, *trailing]``; returns ``A``.

    ``batch`` is the env batch ``B`` (the tensordict's or the spec's). Without this, a
    group of batch ``[*B]`` fails later as a broadcast error deep inside a batched env.
    """
    shape, batch, trailing = tuple(shape), tuple(batch), tuple(trailing)
    n = len(batch)
    if (
        len(shape) == n + 1 + len(trailing)
        and shape[:n] == batch
        and shape[n + 1 :] == trailing
        and (n_agents is None or shape[n] == n_agents)
    ):
        return shape[n]
    agents = "A" if n_agents is None else str(n_agents)
    expected = ", ".join([*map(str, batch), agents, *map(str, trailing)])
    group = _fmt(key[:-1]) if isinstance(key, tuple) and len(key) > 1 else "agents"
    raise ValueError(
        f"{_fmt(key)} has shape {list(shape)}, expected [{expected}] (env batch B = "
        f"{list(batch)}, A robots): the {group!r} group must have batch [*B, A]"
    )


def _check_group_batch(td: TensorDictBase, key: NestedKey, n_agents: int) -> None:
    """The group holding per-robot entry ``key`` has batch ``[*B, A]``. A group created by
    ``td.set(("agents", k), v)`` gets the root's ``[*B]``: every entry has the right shape,
    and a collector stacking such tensordicts fails deep inside tensordict."""
    if not isinstance(key, tuple) or len(key) < 2:
        return
    group = td.get(key[:-1], None)
    expected = (*td.batch_size, n_agents)
    if group is not None and tuple(group.batch_size) != expected:
        raise ValueError(
            f"the {_fmt(key[:-1])!r} group has batch {list(group.batch_size)}, expected {list(expected)} "
            f"(env batch B = {list(td.batch_size)}, {n_agents} robots): build it as "
            f"TensorDict({{...}}, batch_size={list(expected)}) and set it whole, "
            f"td.set({key[:-1][0]!r}, group), not entry by entry with td.set(({key[0]!r}, name), value)"
        )


class _LazyBuffers:
    """Buffers sized at the first call (names in ``_lazy``, registered empty): a loaded
    state dict gives them its shapes before the copy, on this module's device."""

    _lazy: tuple[str, ...] = ()

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        fixed = [b for n, b in self.named_buffers(recurse=False) if n not in self._lazy]
        device = fixed[0].device if fixed else None
        for name in self._lazy:
            saved = state_dict.get(prefix + name)
            if saved is not None:
                setattr(self, name, torch.empty_like(saved, device=device))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)


class _ClonesOwnBuffers:
    """``clone()`` with buffers of its own: TorchRL's ``Transform.clone`` is a shallow copy, so
    a clone's in-place updates (the stage histogram, per-world state) landed in the original."""

    def clone(self):
        out = super().clone()
        for module in out.modules():
            for name, buf in list(module.named_buffers(recurse=False)):
                setattr(module, name, buf.clone())
        return out


class _EnvOnly:
    """Refuses replay buffers, whose sampled rows are not the env's worlds.

    TorchRL gives a transform no link to its buffer; ``ReplayBuffer(transform=...)`` and
    ``rb.append_transform(...)`` put it in eval mode with no env, which is what we test.
    A transform built and called directly stays in train mode. Subclasses say why they
    need the env (``_needs_env``) and what to do instead (``_instead``).
    """

    _needs_env = ""
    _instead = ""

    def _refuse_replay_buffer(self) -> None:
        if self.training or self.parent is not None:
            return
        raise RuntimeError(
            f"{type(self).__name__} cannot run in a replay buffer: {self._needs_env}, and a "
            f"sampled batch has no world identity (its rows are neither env worlds nor "
            f"consecutive steps of one). {self._instead} (Detected: no parent env and eval "
            f"mode, as a replay buffer holds its transforms; to call it on a tensordict "
            f"without an env on purpose, keep it in train mode: transform.train().)"
        )

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        # Our env steps go through _step, so only a caller outside the env gets here,
        # e.g. a buffer's write path with rb.append_transform(t, invert=True).
        self._refuse_replay_buffer()
        return super()._call(next_tensordict)


def _check_names(what: str, given, known: Sequence[str], unique: bool = False) -> None:
    unknown = [n for n in given if n not in known]
    if unknown:
        raise ValueError(f"unknown term(s) in {what}: {unknown}; terms are {tuple(known)}")
    if unique and len(set(given)) != len(list(given)):
        raise ValueError(f"duplicate names in {what}: {list(given)}")


def _check_exact(what: str, given: Mapping[str, float], expected: Sequence[str]) -> None:
    missing = [n for n in expected if n not in given]
    extra = [n for n in given if n not in expected]
    if missing or extra:
        raise ValueError(
            f"{what} must cover exactly {tuple(expected)}: missing {missing}, unexpected {extra}"
        )
