"""A student with memory: a GRU over its own noisy observations, whose state the actor's
MLP reads beside the observation (``student.recurrent_cells``).

Why: the teacher's stage is latched by the stage graph (a box lifted once and set down
again is still S3; a robot whose grasp failed after the box reached the goal is back in
S0), so it is a function of the episode so far, not of the state now. The dual student
without it plateaus at 0.70-0.77 training success; with the stage as an input it reaches
0.93, and with the stage recomputed from the exact state now (no latching) 0.74
(docs/history/distillation.md). Memory is what is missing, and a GRU is the deployable form of it.

The GRU state travels in the tensordict: the actor reads ``HIDDEN`` (the state before this
step) and ``"step_count"`` (0 on an episode's first step, where the state starts from
zeros) and writes ``HIDDEN_NEXT``; :func:`carry_state` moves it into the next step's
input. On a batch ``[B, T]`` (a PPO minibatch of whole rollout segments) the actor runs the
GRU over the T steps from the stored state of the first one: backpropagation through the
segment (truncated there), as rsl_rl trains its recurrent policies.
"""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torch import nn

from pnp.training.keys import OBS
from pnp.training.models import AgentNet, ObsNorm
from pnp.training.stage_ensemble import call_head

HIDDEN = ("agents", "student_hidden")
HIDDEN_NEXT = ("agents", "student_hidden_next")
STEP_COUNT = "step_count"


class RecurrentStudentNet(AgentNet):
    """:class:`AgentNet` over [normalised observation | GRU state], parameters shared over
    agents; each agent has its own GRU state ``[*B, A, hidden]``.

    ``forward(obs, hidden, step_count)`` on one step (``obs`` ``[N, A, D]``) or on segments
    (``[B, T, A, D]``, ``hidden`` read at the first step only); returns the head's outputs
    and the GRU state after each step."""

    def __init__(self, n_obs: int, n_out: int, n_agents: int, cells, hidden: int, head: nn.Module | None = None,
                 obs_norm: ObsNorm | None = None, n_stages: int = 0, stage_coeff: float = 0.0):
        if hidden < 1:
            raise ValueError(f"student.recurrent_cells={hidden}: a GRU needs at least one cell (0 means no GRU)")
        if stage_coeff < 0:
            raise ValueError(f"student.stage_loss_coeff={stage_coeff}: must be >= 0")
        super().__init__(n_obs + hidden, n_out, n_agents, False, cells, head=head, obs_norm=obs_norm)
        self.hidden_size, self.stage_coeff = hidden, float(stage_coeff)
        self.gru = nn.GRUCell(n_obs, hidden)
        # Training only: the stage read off the GRU state, trained towards the env's stage.
        self.stage_head = nn.Linear(hidden, n_stages) if stage_coeff > 0 else None
        self._stage_logits: torch.Tensor | None = None

    def stage_loss(self, stage_one_hot: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``stage_coeff`` x cross-entropy of the stage read off the GRU states of the last
        forward against ``stage_one_hot``, and the share read right."""
        if self._stage_logits is None:
            raise RuntimeError("stage_loss needs a forward first (and student.stage_loss_coeff > 0)")
        logits, target = self._stage_logits.flatten(0, -2), stage_one_hot.argmax(-1).flatten()
        accuracy = (logits.argmax(-1) == target).float().mean().detach()
        return self.stage_coeff * nn.functional.cross_entropy(logits, target), accuracy

    def _step(self, x: torch.Tensor, h: torch.Tensor, step_count: torch.Tensor) -> torch.Tensor:
        h = torch.where((step_count == 0).unsqueeze(-1), torch.zeros_like(h), h)  # [*, 1, 1] over agents, cells
        return self.gru(x.reshape(-1, x.shape[-1]), h.reshape(-1, self.hidden_size)).reshape(h.shape)

    def forward(self, obs: torch.Tensor, hidden: torch.Tensor, step_count: torch.Tensor):
        x = self.obs_norm(obs)
        if obs.dim() == 3:  # one step of N worlds
            h = self._step(x, hidden, step_count)
        elif obs.dim() == 4:  # segments [B, T]: from the state stored at their first step
            state, out = hidden[:, 0], []
            for t in range(obs.shape[1]):
                state = self._step(x[:, t], state, step_count[:, t])
                out.append(state)
            h = torch.stack(out, 1)
        else:
            raise ValueError(f"RecurrentStudentNet takes observations [N, A, D] or [B, T, A, D], "
                             f"got {tuple(obs.shape)}")
        if self.stage_head is not None:
            self._stage_logits = self.stage_head(h)
        y = self.mlp(torch.cat([x, h], -1))
        return (*call_head(self.head, y, obs[..., :0]), h)


def recurrent_net(policy) -> RecurrentStudentNet | None:
    """The recurrent net inside a policy, if it has one (a scripted policy, a function, has none)."""
    if not isinstance(policy, nn.Module):
        return None
    return next((m for m in policy.modules() if isinstance(m, RecurrentStudentNet)), None)


def init_state(td: TensorDictBase, actor) -> TensorDictBase:
    """Zero GRU states in a freshly reset ``td`` when ``actor`` is recurrent (else ``td`` as is)."""
    net = recurrent_net(actor)
    if net is not None:
        n_agents = td.get(OBS).shape[-2]
        td.set(HIDDEN, torch.zeros(*td.batch_size, n_agents, net.hidden_size))
    return td


def carry_state(step: TensorDictBase, carried: TensorDictBase) -> TensorDictBase:
    """The GRU state a recurrent policy wrote in ``step`` becomes ``carried``'s input (the
    caller asks :func:`recurrent_net` once, not every step); an episode that restarted
    zeroes it on its first step itself."""
    return carried.set(HIDDEN, step.get(HIDDEN_NEXT))
