"""A tiny batched multi-agent env whose observation is a known function of the step and
episode counts (column d of agent a: count + 1000 episode + 10 a + 100 d), so noise and
history can be read off exactly. Batch [N], group "agents" [N, A], observation width D."""
from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

N, A, D = 4, 2, 6


class CountingObsEnv(EnvBase):
    def __init__(self, n_worlds: int = N, episode_len=(100,) * N):
        super().__init__(batch_size=(n_worlds,))
        n = n_worlds
        self.episode_len = torch.tensor(episode_len).reshape(n, 1)
        self.count = torch.zeros(n, 1, dtype=torch.long)
        self.episode = torch.full((n, 1), -1, dtype=torch.long)
        group = dict(shape=(n, A))
        obs = Composite(observation=Unbounded((n, A, D)), **group)
        self.observation_spec = Composite(agents=obs, shape=(n,))
        self.action_spec = Composite(agents=Composite(action=Unbounded((n, A, 1)), **group), shape=(n,))
        self.reward_spec = Composite(agents=Composite(reward=Unbounded((n, A, 1)), **group), shape=(n,))
        self.done_spec = Composite(
            done=Categorical(2, (n, 1), dtype=torch.bool),
            terminated=Categorical(2, (n, 1), dtype=torch.bool),
            shape=(n,),
        )

    def _obs(self) -> TensorDict:
        n = self.count.shape[0]
        base = (self.count + 1000 * self.episode).reshape(n, 1, 1)
        obs = (base + 10 * torch.arange(A).reshape(1, A, 1) + 100 * torch.arange(D)).float()
        done = self.count >= self.episode_len
        agents = TensorDict(observation=obs, batch_size=(n, A))
        return TensorDict(agents=agents, done=done, terminated=done.clone(), batch_size=(n,))

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        reset = None if tensordict is None else tensordict.get("_reset", None)
        mask = torch.ones(self.count.shape, dtype=torch.bool) if reset is None else reset.reshape(-1, 1)
        self.count[mask] = 0
        self.episode[mask] += 1
        return self._obs()

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        self.count += 1
        out = self._obs()
        out.set(("agents", "reward"), torch.zeros(self.count.shape[0], A, 1))
        return out

    def _set_seed(self, seed: int | None) -> None:
        pass


def steps(env, td, n: int):
    """``n`` steps with zero actions from ``td``: the observations seen [n, N, A, D] and the last td."""
    out = []
    for _ in range(n):
        td = td.set(("agents", "action"), torch.zeros(N, A, 1))
        _, td = env.step_and_maybe_reset(td)
        out.append(td[("agents", "observation")].clone())
    return torch.stack(out), td
