"""The stage transition graph of a multi-stage task (paper Sec. III-B, Fig. 3), task-free.

Stages form a chain ``S0 -> S1 -> ... -> S_last``: the edge ``S_i -> S_{i+1}`` is taken
when its forward condition ``conditions[i]`` holds. A few backward edges (pickup and
release in the paper) let a robot fall back when the condition that brought it into its
stage is lost, so that it learns recovery. Plain python and torch, no TorchRL:
:class:`StageTransition` wraps :meth:`StageGraph.next_stage`. Pick-and-place's graph is
``pnp.task.stage_graph``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence, Union

import torch

StageRef = Union[int, str]


@dataclass(frozen=True)
class StageGraph:
    """Stages, forward conditions and allowed backward edges, validated at construction.

    Args:
        stages: stage names, in chain order (``stages[0]`` is where episodes start).
        conditions: ``conditions[i]`` names the forward condition of ``S_i -> S_{i+1}``.
        backward_edges: ``(from, to)`` pairs, by index or name, with ``to < from``; at
            most one per stage.
        forward_edges: optional, only so that a config file can spell the whole graph;
            must be the chain ``(i, i+1)`` (checked: reachability, no cycle, order).
    """

    stages: tuple[str, ...]
    conditions: tuple[str, ...]
    backward_edges: tuple[tuple[int, int], ...] = ()
    forward_edges: tuple[tuple[int, int], ...] | None = None
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        stages = tuple(self.stages)
        conditions = tuple(self.conditions)
        _no_duplicates("stage", stages)
        _no_duplicates("condition", conditions)
        if len(stages) < 1:
            raise ValueError("a StageGraph needs at least one stage")
        if len(conditions) != len(stages) - 1:
            raise ValueError(
                f"expected {len(stages) - 1} conditions (one per edge S_i -> S_i+1 of "
                f"{len(stages)} stages), got {len(conditions)}: {conditions}"
            )
        object.__setattr__(self, "stages", stages)
        object.__setattr__(self, "conditions", conditions)
        fwd = None
        if self.forward_edges is not None:
            fwd = tuple((self._index(a), self._index(b)) for a, b in self.forward_edges)
            self._check_forward_chain(fwd)
        object.__setattr__(self, "forward_edges", fwd)
        back = tuple((self._index(a), self._index(b)) for a, b in self.backward_edges)
        for a, b in back:
            if b >= a:
                kind = "a self-loop" if a == b else "goes forward"
                raise ValueError(
                    f"backward edge {stages[a]} -> {stages[b]} {kind}; backward edges must "
                    "go to an earlier stage"
                )
        sources = [a for a, _ in back]
        for a in set(sources):
            if sources.count(a) > 1:
                raise ValueError(f"stage {stages[a]!r} has more than one backward edge")
        object.__setattr__(self, "backward_edges", back)

    @property
    def n_stages(self) -> int:
        return len(self.stages)

    @property
    def last_stage(self) -> int:
        return len(self.stages) - 1

    def _index(self, ref: StageRef) -> int:
        if isinstance(ref, str):
            if ref not in self.stages:
                raise ValueError(f"unknown stage {ref!r}; stages are {self.stages}")
            return self.stages.index(ref)
        ref = int(ref)
        if not 0 <= ref < len(self.stages):
            raise ValueError(f"stage index {ref} out of range [0, {len(self.stages)})")
        return ref

    def _check_forward_chain(self, edges: tuple[tuple[int, int], ...]) -> None:
        n = len(self.stages)
        out: dict[int, list[int]] = {i: [] for i in range(n)}
        for a, b in edges:
            out[a].append(b)
        # Cycle check first (DFS colours), then reachability from S0, then chain order.
        state = [0] * n
        for root in range(n):
            if state[root]:
                continue
            state[root] = 1
            stack = [(root, iter(out[root]))]
            while stack:
                node, it = stack[-1]
                nxt = next(it, None)
                if nxt is None:
                    state[node] = 2
                    stack.pop()
                elif state[nxt] == 1:
                    raise ValueError(f"forward cycle through stage {self.stages[nxt]!r}")
                elif state[nxt] == 0:
                    state[nxt] = 1
                    stack.append((nxt, iter(out[nxt])))
        seen, todo = {0}, [0]
        while todo:
            for b in out[todo.pop()]:
                if b not in seen:
                    seen.add(b)
                    todo.append(b)
        missing = [self.stages[i] for i in range(n) if i not in seen]
        if missing:
            raise ValueError(f"unreachable stage(s) from {self.stages[0]!r}: {missing}")
        chain = {(i, i + 1) for i in range(n - 1)}
        if set(edges) != chain:
            raise ValueError(
                f"forward edges must be the chain S_i -> S_i+1 in the order of `stages`; "
                f"got {sorted(edges)}"
            )

    def _lookups(self, device: torch.device) -> tuple[torch.Tensor, ...]:
        """Per-stage index tensors, cached per device.

        Condition columns are padded with a False column (index C) and a True column
        (index C+1): the last stage has no forward condition (never moves on), S0 has no
        entry condition (can never lose it).
        """
        if device not in self._cache:
            n, c = len(self.stages), len(self.conditions)
            out_cond = list(range(n - 1)) + [c]
            in_cond = [c + 1] + list(range(n - 1))
            back_to = list(range(n))  # no edge: stay where you are
            for a, b in self.backward_edges:
                back_to[a] = b
            self._cache[device] = tuple(
                torch.tensor(v, dtype=torch.long, device=device)
                for v in (out_cond, in_cond, back_to)
            )
        return self._cache[device]

    def next_stage(self, stage: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        """One transition step for any batch shape.

        Args:
            stage: int64 ``[...]``, current stage indices.
            cond: bool ``[..., n_conditions]``, in the order of :attr:`conditions`.

        Returns:
            int64 ``[...]``: ``stage + 1`` if the current stage's forward condition holds;
            else the backward edge's target if the condition that brought the robot here
            (``conditions[stage - 1]``) no longer holds and such an edge exists; else
            ``stage``.
        """
        if cond.shape[-1] != len(self.conditions):
            raise ValueError(
                f"cond has {cond.shape[-1]} columns, the graph has "
                f"{len(self.conditions)} conditions {self.conditions}"
            )
        if cond.shape[:-1] != stage.shape:
            raise ValueError(f"stage {tuple(stage.shape)} vs cond {tuple(cond.shape)}")
        out_cond, in_cond, back_to = self._lookups(stage.device)
        stage = stage.long()
        pad = torch.zeros((*cond.shape[:-1], 2), dtype=torch.bool, device=cond.device)
        pad[..., 1] = True
        cond = torch.cat([cond.bool(), pad], dim=-1)
        fwd = cond.gather(-1, out_cond[stage].unsqueeze(-1)).squeeze(-1)
        kept = cond.gather(-1, in_cond[stage].unsqueeze(-1)).squeeze(-1)
        return torch.where(fwd, stage + 1, torch.where(kept, stage, back_to[stage]))


def _no_duplicates(what: str, names: Sequence[str]) -> None:
    dup = sorted({n for n in names if list(names).count(n) > 1})
    if dup:
        raise ValueError(f"duplicate {what} name(s): {dup}")
