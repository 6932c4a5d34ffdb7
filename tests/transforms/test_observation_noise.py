"""``ObservationNoise`` on a tiny env whose observation is a known function of the step count.

Column d of slot (w, a) reads ``count[w] + 1000 * episode[w] + 10 * a + 100 * d``: column 0
is left clean in every test, so the clean value of any column is column 0 + 100 d.
"""
from __future__ import annotations

import copy
import functools

import pytest
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import SerialEnv, TransformedEnv
from torchrl.envs.utils import check_env_specs

from pnp.transforms import ObservationNoise

from ._counting_env import A, D, N, CountingObsEnv, steps

FIELDS = {"pos": ((1, 3), 0.5), "obj": (slice(3, 5), 0.1)}  # columns 0 and 5 stay clean
OBS = ("agents", "observation")


def make_env(episode_len=(100,) * N, **noise) -> TransformedEnv:
    noise.setdefault("fields", FIELDS)
    return TransformedEnv(CountingObsEnv(len(episode_len), episode_len), ObservationNoise(**noise))


def seen(r: TensorDictBase, key=OBS) -> torch.Tensor:
    """What the policy sees at t (reset observations included): ``[N, T, A, D]``."""
    return r[key]


def clean(obs: torch.Tensor) -> torch.Tensor:
    return obs[..., :1] + 100 * torch.arange(D)


def rollout(env, steps):
    return env.rollout(steps, break_when_any_done=False)


@pytest.mark.parametrize("out_key", [None, ("agents", "noisy")], ids=["in_place", "out_key"])
def test_noise_std_per_field(out_key):
    env = make_env(episode_len=(100,) * 64, out_key=out_key)
    check_env_specs(env)
    r = env.rollout(60, break_when_any_done=False)
    noisy = r["next", out_key or OBS]
    diff = noisy - (r["next", OBS] if out_key else clean(noisy))
    for name, ((start, stop), sigma) in {"pos": ((1, 3), 0.5), "obj": ((3, 5), 0.1)}.items():
        assert abs(diff[..., start:stop].std().item() / sigma - 1) < 0.1, name
    assert torch.equal(diff[..., [0, 5]], torch.zeros_like(diff[..., [0, 5]]))


def test_dropout_holds_the_last_noisy_value_for_its_duration():
    env = make_env(dropouts={"pos": (1.0, 0.3, 0.3)}, dt=0.1)
    full = seen(rollout(env, 12))
    obs, ref = full[..., 1:3], clean(full)[..., 1:3]
    # Seen at 0 (reset), held at 1-3, seen at 4, held at 5-7, seen at 8 ...
    for t in (1, 2, 3):
        assert torch.equal(obs[:, t], obs[:, 0])
        assert torch.equal(obs[:, t + 4], obs[:, 4])
    assert (obs[:, 4] != obs[:, 3]).all() and (obs[:, 8] != obs[:, 7]).all()
    assert (obs[:, 1] != ref[:, 0]).all()  # the noisy value, not the clean one
    assert (obs[:, 4] - ref[:, 4]).abs().max() < 5  # moved on to a fresh (noisy) value


def test_reset_clears_the_dropout_of_reset_worlds_only():
    # World 0 ends every 2 steps, the others never; dropouts hold 5 steps, no noise.
    fields = {"pos": ((1, 3), 0.0)}
    env = make_env(episode_len=(2, 100, 100, 100), fields=fields, dropouts={"pos": (1.0, 0.5, 0.5)})
    obs = seen(rollout(env, 8))
    pos, ref = obs[..., 1:3], clean(obs)[..., 1:3]
    # t=2 is world 0's reset observation of episode 1: seen (cleared), then held.
    assert torch.equal(pos[0, 2], ref[0, 2]) and ref[0, 2, 0, 0] == 1000 + 100
    assert torch.equal(pos[0, 3], pos[0, 2])
    # The other worlds are not touched by it: held at t=0's value for 5 steps, then seen.
    for t in range(1, 6):
        assert torch.equal(pos[1:, t], pos[1:, 0])
    assert torch.equal(pos[1:, 6], ref[1:, 6])


def test_seeded_generator_is_reproducible():
    cfg = dict(dropouts={"pos": (0.3, 0.1, 0.5)}, generator_seed=7)
    a, b = rollout(make_env(**cfg), 20), rollout(make_env(**cfg), 20)
    assert torch.equal(seen(a), seen(b))
    other = rollout(make_env(**{**cfg, "generator_seed": 8}), 20)
    assert not torch.equal(seen(a), seen(other))


def test_state_dict_round_trip_mid_rollout():
    cfg = dict(dropouts={"pos": (0.3, 0.1, 0.5)})
    env, fresh = make_env(generator_seed=7, **cfg), make_env(generator_seed=99, **cfg)
    _, td = steps(env, env.reset(), 6)
    steps(fresh, fresh.reset(), 6)  # same base env state, other noise state
    state = copy.deepcopy(env.transform.state_dict())
    assert {"held", "hold_left", "_extra_state"} <= set(state)
    fresh.transform.load_state_dict(state)
    expected, _ = steps(env, td.clone(), 10)
    got, _ = steps(fresh, td.clone(), 10)
    assert torch.equal(expected, got)
    unsized = ObservationNoise(FIELDS, **cfg)  # lazy buffers take the saved shapes
    unsized.load_state_dict(state)
    assert unsized.hold_left.shape == (N, A, 1) and unsized.generator is not None


@pytest.mark.parametrize(
    "cfg, match",
    [
        (dict(fields={"a": ((0, 3), 0.1), "b": ((2, 4), 0.1)}), "'a'.*'b'.*overlap"),
        (dict(fields={"a": ((0, 3), 0.1)}, dropouts={"ghost": (0.1, 0.1, 0.2)}), "'ghost'.*unknown field"),
        (dict(fields={"a": ((0, 3), -1.0)}), r"'a'.*std.*-1\.0"),
        (dict(fields={"a": (slice(0, 4, 2), 0.1)}), "'a'.*step"),
        (dict(fields={"a": ((0, 3), 0.1)}, dropouts={"a": (1.5, 0.1, 0.2)}), "'a'.*probability.*1.5"),
    ],
)
def test_bad_config_is_named(cfg, match):
    with pytest.raises(ValueError, match=match):
        ObservationNoise(**cfg)


def test_field_outside_the_observation_is_named():
    env = make_env(fields={"far": ((4, 9), 0.1)})
    with pytest.raises(ValueError, match=r"'far' \[4, 9\] outside agents.observation.*6 columns"):
        env.reset()


def test_agent_group_needs_batch_B_A():
    td = TensorDict(agents=TensorDict(observation=torch.zeros(N, D), batch_size=(N,)), batch_size=(N,))
    with pytest.raises(ValueError, match=r"agents.observation has shape \[4, 6\], expected \[4, A, 6\]"):
        ObservationNoise(FIELDS)(td)


@pytest.mark.parametrize("how", ["transform=", "append", "invert"])
def test_in_replay_buffer_is_refused(how):
    t = ObservationNoise(FIELDS, dropouts={"pos": (0.1, 0.1, 0.2)})
    rb = ReplayBuffer(storage=LazyTensorStorage(8), batch_size=2, transform=t if how == "transform=" else None)
    if how != "transform=":
        rb.append_transform(t, invert=how == "invert")
    data = rollout(make_env(), 3).reshape(-1)
    with pytest.raises(RuntimeError, match="cannot run in a replay buffer.*no world identity.*in the env"):
        rb.extend(data)
        rb.sample()


def test_outside_serial_env():
    make = functools.partial(CountingObsEnv, 2, (3, 100))
    t = ObservationNoise(FIELDS, dropouts={"pos": (0.5, 0.1, 0.3)}, generator_seed=0)
    env = TransformedEnv(SerialEnv(2, make), t)
    r = rollout(env, 5)
    assert r["next", OBS].shape == (2, 2, 5, A, D)
    assert t.hold_left.shape == (2, 2, A, 1)
    obs = r[OBS]
    assert torch.equal(obs[..., [0, 5]], clean(obs)[..., [0, 5]])
