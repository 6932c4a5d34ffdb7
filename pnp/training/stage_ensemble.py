"""One network per stage behind one module: the per-stage baselines' actors and critics.

Bendikas et al. and Erskine et al. train one policy (and critic) per stage of the task.
:class:`StageEnsemble` holds them as members and computes each (world, robot) with the
member its stage selects through a routing table, so a batch costs one member's forward
whatever the stage mix; or, with ``concat``, with every member, outputs side by side
(Erskine's critics: each stage's advantage needs that stage's value at every state).
"""
from __future__ import annotations

from typing import Sequence

import torch
from torch import nn


def call_head(head: nn.Module, y: torch.Tensor, stage: torch.Tensor):
    """``head(y)``, or ``head(y, stage)`` for a head that reads the stage (``takes_stage``)."""
    return head(y, stage) if getattr(head, "takes_stage", False) else head(y)


class StageEnsemble(nn.Module):
    """Members ``[obs | stage one-hot] -> out``, selected per (world, robot) by ``route[stage]``.

    Args:
        members: one network per stage, each called as ``member(x, stage_one_hot)`` on
            ``[B, A, ...]`` (``pnp.training.models.AgentNet`` without its own head or norm).
        obs_norm: applied once to the observation before any member (shared with the critic).
        head: applied to the routed (or concatenated) output: the actor's parameter head,
            the critic's PopArt.
        concat: every member on every sample, outputs concatenated on the last dim.

    ``route`` (a buffer, in the state dict): stage -> member; the identity by default
    (Erskine), all one member for Bendikas' sub-task (its policy acts in every stage).
    """

    def __init__(self, members: Sequence[nn.Module], obs_norm: nn.Module | None = None, head: nn.Module | None = None,
                 concat: bool = False):
        super().__init__()
        if not members:
            raise ValueError("StageEnsemble needs at least one member")
        self.members = nn.ModuleList(members)
        self.obs_norm = obs_norm if obs_norm is not None else nn.Identity()
        self.head = head if head is not None else nn.Identity()
        self.concat = bool(concat)
        self.register_buffer("route", torch.arange(len(members)))

    def forward(self, obs: torch.Tensor, stage: torch.Tensor):
        x = self.obs_norm(obs)
        if self.concat:
            return call_head(self.head, torch.cat([m(x, stage) for m in self.members], -1), stage)
        if bool((self.route == self.route[0]).all()):  # one member acts everywhere (Bendikas' sub-task)
            return call_head(self.head, self.members[int(self.route[0])](x, stage), stage)
        # Rows by member: data-dependent shapes, so not under vmap (GAE's value pass calls
        # only the critics, which are concatenated or single-member).
        lead = x.shape[:-2]  # any batch dims before [A, n]
        x, stage = x.reshape(-1, *x.shape[-2:]), stage.reshape(-1, *stage.shape[-2:])
        member = self.route[stage.argmax(-1)]  # [B, A]
        out = None
        for k in member.unique().tolist():
            mine = member == k
            rows = mine.any(-1)  # worlds with a robot of this member: a centralised net needs the whole world
            y = self.members[k](x[rows], stage[rows])
            if out is None:
                out = y.new_zeros(*member.shape, y.shape[-1])
            out[rows] = torch.where(mine[rows].unsqueeze(-1), y, out[rows])
        return call_head(self.head, out.reshape(*lead, *out.shape[-2:]), stage.reshape(*lead, *stage.shape[-2:]))

    def route_all_to(self, member: int) -> None:
        """Every stage to one member (Bendikas' sub-task ``member``)."""
        if not 0 <= member < len(self.members):
            raise ValueError(f"member {member} not in [0, {len(self.members)})")
        self.route.fill_(member)

    @torch.no_grad()
    def copy_member(self, src: int, dst: int) -> None:
        """Member ``dst`` becomes a copy of member ``src`` (its parameter objects are kept)."""
        self.members[dst].load_state_dict(self.members[src].state_dict())

    def used_members(self) -> list[int]:
        """The members that act: all when concatenated, else those the route table names."""
        return list(range(len(self.members))) if self.concat else sorted(set(self.route.tolist()))


def _count(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def parameter_count(actor_net: nn.Module, critic_net: nn.Module) -> dict[str, int]:
    """Trainable parameters: ``actor`` and ``critic`` as trained, and ``inference``, the
    actor parameters that act in a deployed policy (a per-stage ensemble: the members its
    route table names; Bendikas' last policy alone)."""
    inference = _count(actor_net)
    if isinstance(actor_net, StageEnsemble):
        inference = _count(actor_net.head) + sum(_count(actor_net.members[k]) for k in actor_net.used_members())
    return {"actor": _count(actor_net), "critic": _count(critic_net), "inference": inference}
