"""A deterministic batched multi-agent env that emits what the curriculum reads.

Batch ``[N]``, group ``"agents"`` of ``A`` robots. Slot (w, a) can satisfy its first
``reach[w, a]`` stage conditions: ``cond_i = (count > i) and (i < reach)``, so its stage
climbs one step per env step up to ``reach``. After ``lose_after`` steps every condition
is lost (to exercise backward edges). World w is done after ``episode_len[w]`` steps.
Reward terms are constant ``term_values``. With ``emit_stage`` the env also writes the
stage ``min(count, reach)`` and the episode-final stage itself, as an env that tracks its
own stages would (to use a reward schedule without ``StageTransition``).
"""
from __future__ import annotations

from typing import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import Compose, EnvBase, StepCounter, TransformedEnv

from pnp.task.stage_graph import pnp_default_reward_config, pnp_default_stage_graph
from pnp.task.terms import CONDITIONS, REWARD_TERMS
from pnp.transforms import StageTransition, make_reward_schedule


class ToyStageEnv(EnvBase):
    def __init__(
        self,
        n_worlds: int = 3,
        n_agents: int = 2,
        n_conditions: int = 6,
        n_terms: int = 4,
        episode_len: int | Sequence[int] = 8,
        reach: torch.Tensor | None = None,
        lose_after: int | None = None,
        term_values: Sequence[float] | None = None,
        emit_stage: bool = False,
    ):
        super().__init__(batch_size=(n_worlds,))
        n, a = n_worlds, n_agents
        if reach is None:
            reach = (torch.arange(n)[:, None] + torch.arange(a)[None, :]) % (n_conditions + 1)
        self.reach = torch.as_tensor(reach).reshape(n, a)
        lens = [episode_len] * n if isinstance(episode_len, int) else list(episode_len)
        self.episode_len = torch.tensor(lens).reshape(n, 1)
        self.lose_after = lose_after
        values = torch.ones(n_terms) if term_values is None else torch.tensor(term_values)
        self.term_values = values.float()
        self.n_conditions = n_conditions
        self.emit_stage = emit_stage
        self.count = torch.zeros(n, 1, dtype=torch.long)
        agents = dict(shape=(n, a))
        self.observation_spec = Composite(
            agents=Composite(
                observation=Unbounded((n, a, 1)),
                stage_conditions=Categorical(2, (n, a, n_conditions), dtype=torch.bool),
                reward_terms=Unbounded((n, a, n_terms)),
                **agents,
            ),
            shape=(n,),
        )
        if emit_stage:
            group = self.observation_spec["agents"]
            group["stage"] = Categorical(n_conditions + 1, (n, a, 1), dtype=torch.long)
            group["episode_stage"] = Unbounded((n, a, 1), dtype=torch.long)
        self.action_spec = Composite(
            agents=Composite(action=Unbounded((n, a, 1)), **agents), shape=(n,)
        )
        self.reward_spec = Composite(
            agents=Composite(reward=Unbounded((n, a, 1)), **agents), shape=(n,)
        )
        self.done_spec = Composite(
            done=Categorical(2, (n, 1), dtype=torch.bool),
            terminated=Categorical(2, (n, 1), dtype=torch.bool),
            shape=(n,),
        )

    def _obs(self) -> TensorDict:
        n, a = self.reach.shape
        i = torch.arange(self.n_conditions)
        cond = (self.count[:, :, None] > i) & (i < self.reach[:, :, None])
        if self.lose_after is not None:
            cond &= (self.count <= self.lose_after)[:, :, None]
        done = self.count >= self.episode_len
        agents = TensorDict(
            observation=self.count.float().expand(n, a).unsqueeze(-1).clone(),
            stage_conditions=cond,
            reward_terms=self.term_values.expand(n, a, -1).clone(),
            batch_size=(n, a),
        )
        if self.emit_stage:
            stage = torch.minimum(self.count, self.reach).unsqueeze(-1)
            agents.set("stage", stage)
            agents.set("episode_stage", torch.where(done[:, :, None], stage, -1))
        return TensorDict(agents=agents, done=done, terminated=done.clone(), batch_size=(n,))

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        reset = None if tensordict is None else tensordict.get("_reset", None)
        if reset is None:
            self.count.zero_()
        else:
            self.count[reset.reshape(-1)] = 0
        return self._obs()

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        self.count += 1
        out = self._obs()
        out.set(("agents", "reward"), torch.zeros(*self.reach.shape, 1))
        return out

    def _set_seed(self, seed: int | None) -> None:
        pass


def make_toy_env(**kwargs) -> ToyStageEnv:
    return ToyStageEnv(**kwargs)


def make_curriculum(kind: str, chain: bool = False):
    """``"stage"``: ``StageTransition`` alone; else the reward schedule ``kind``, after a
    ``StepCounter`` and ``StageTransition`` when ``chain``. Module level for pickling."""
    stage = StageTransition(pnp_default_stage_graph(), one_hot_key=("agents", "stage_one_hot"))
    if kind == "stage":
        return stage
    schedule = make_reward_schedule(kind, K=2.0, mu_min=0.1, **pnp_default_reward_config())
    return Compose(StepCounter(max_steps=5), stage, schedule) if chain else schedule


def make_pnp_toy_env(emit_stage: bool = False) -> ToyStageEnv:
    """Toy env with the PnP term and condition counts."""
    reach = torch.tensor([[0, 6], [3, 5], [6, 6]])
    return ToyStageEnv(n_terms=len(REWARD_TERMS), n_conditions=len(CONDITIONS), episode_len=[4, 5, 6], reach=reach,
                       emit_stage=emit_stage)


def make_transformed(kind: str, chain: bool = True, emit_stage: bool = False):
    return TransformedEnv(make_pnp_toy_env(emit_stage), make_curriculum(kind, chain))
