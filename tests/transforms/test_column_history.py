"""``ColumnHistory`` on the tiny counting env of ``_counting_env``.

Column d of slot (w, a) reads ``count[w] + 1000 * episode[w] + 10 * a + 100 * d``. The
history is of columns 1-2 and columns 4-5 are dropped, so the output is
``[c0 c1 c2 c3 | c1 c2 (t) | c1 c2 (t-1) | c1 c2 (t-2)]``: column 0 stays clean and
tells the episode's start (``count == 0``).
"""
from __future__ import annotations

import copy
import functools

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import Compose, SerialEnv, TransformedEnv
from torchrl.envs.utils import check_env_specs

from pnp.transforms import ColumnHistory, ObservationNoise

from ._counting_env import A, D, N, CountingObsEnv, steps

COLS, L, DROP = (1, 3), 3, [(4, 6)]
K, KEPT = COLS[1] - COLS[0], D - 2  # columns 0-3 kept
WIDTH = KEPT + L * K
OBS = ("agents", "observation")


def make_env(episode_len=(100,) * N, noise: dict | None = None, **kw) -> TransformedEnv:
    kw = {"columns": COLS, "length": L, "drop": DROP, **kw}
    t = ColumnHistory(**kw)
    if noise is not None:
        t = Compose(ObservationNoise(**noise), t)
    return TransformedEnv(CountingObsEnv(len(episode_len), episode_len), t)


def rollout(env, steps):
    return env.rollout(steps, break_when_any_done=False)


def history(out: torch.Tensor) -> torch.Tensor:
    """``[..., WIDTH]`` -> ``[..., L, K]``, most recent first."""
    return out[..., KEPT:].unflatten(-1, (L, K))


def expected_history(out: torch.Tensor) -> torch.Tensor:
    """From the output ``[N, T, A, WIDTH]`` seen at t: entry j at t is columns 1-2 at
    ``max(t - j, episode start)``, read from the kept (current) columns of that step."""
    cur, starts = out[..., COLS[0] : COLS[1]], out[..., 0, 0] % 1000 == 0  # [N, T]
    exp = torch.empty(*out.shape[:-1], L, K)
    for n in range(out.shape[0]):
        start = 0
        for t in range(out.shape[1]):
            start = t if starts[n, t] else start
            for j in range(L):
                exp[n, t, :, j] = cur[n, max(t - j, start)]
    return exp


@pytest.mark.parametrize("out_key", [None, ("agents", "with_history")], ids=["in_place", "out_key"])
def test_specs_and_width(out_key):
    env = make_env(out_key=out_key)
    check_env_specs(env)
    spec = env.observation_spec[out_key or OBS]
    assert spec.shape == (N, A, WIDTH) and spec.dtype == torch.float32
    r = rollout(env, 4)
    assert r["next", out_key or OBS].shape == (N, 4, A, WIDTH)
    if out_key is not None:  # the input is left as it was
        assert r["next", OBS].shape == (N, 4, A, D)
        assert torch.equal(r["next", out_key][..., :KEPT], r["next", OBS][..., :KEPT])


def test_history_is_the_last_values_most_recent_first():
    out = rollout(make_env(), 6)[OBS]  # seen at t = 0 (reset) .. 5
    count = torch.arange(6).reshape(1, 6, 1, 1, 1)
    a = torch.arange(A).reshape(1, 1, A, 1, 1)
    j = torch.arange(L).reshape(1, 1, 1, L, 1)
    cols = 100 * torch.arange(*COLS).reshape(1, 1, 1, 1, K)
    exp = ((count - j).clamp(min=0) + 10 * a + cols).float().expand(N, 6, A, L, K)
    assert torch.equal(history(out), exp)
    assert torch.equal(history(out[:, 0]), history(out[:, 0])[..., :1, :].expand(N, A, L, K))  # constant
    assert torch.equal(history(out), expected_history(out))
    assert torch.equal(out[..., :KEPT], (count[..., 0] + 10 * a[..., 0] + 100 * torch.arange(KEPT)).float()
                       .expand(N, 6, A, KEPT))


def test_partial_reset_refills_only_the_reset_worlds():
    r = rollout(make_env(episode_len=(2, 100, 100, 100)), 7)
    out = r[OBS]
    assert torch.equal(history(out), expected_history(out))
    # World 0's reset at t=2 refills it with episode 1's first value, constant.
    assert torch.equal(history(out[0, 2]), (1000 + 10 * torch.arange(A).reshape(A, 1, 1)
                                            + 100 * torch.arange(*COLS)).float().expand(A, L, K))
    # Other worlds: the reset output shows their history as it was after the step.
    assert torch.equal(out[1:, 2], r["next", OBS][1:, 1])
    assert torch.equal(history(out[1:, 3])[:, :, 1], history(out[1:, 2])[:, :, 0])


def test_state_dict_round_trip_mid_rollout():
    lens = (3, 100, 100, 100)
    env, fresh = make_env(lens), make_env(lens)
    _, td = steps(env, env.reset(), 5)
    steps(fresh, fresh.reset(), 5)  # same base env state ...
    fresh.transform.history.zero_()  # ... other history
    state = copy.deepcopy(env.transform.state_dict())
    assert set(state) == {"history"}
    fresh.transform.load_state_dict(state)
    expected, _ = steps(env, td.clone(), 6)
    got, _ = steps(fresh, td.clone(), 6)
    assert torch.equal(expected, got)
    unsized = ColumnHistory(COLS, L, drop=DROP)  # the lazy buffer takes the saved shape
    unsized.load_state_dict(state)
    assert unsized.history.shape == (N, A, L, K)


@pytest.mark.parametrize(
    "cfg, match",
    [
        (dict(columns=(3, 3), length=2), r"columns.*\(3, 3\)"),
        (dict(columns=(-1, 2), length=2), r"columns.*\(-1, 2\)"),
        (dict(columns=(0, 2), length=0), "length.*0"),
        (dict(columns=(0, 2), length=2.5), "length.*2.5"),
        (dict(columns=(0, 2), length=2, drop=[(5, 4)]), r"drop\[0\].*\(5, 4\)"),
        (dict(columns=(0, 2), length=2, drop=[(4, 6), (0, 3), (2, 4)]), r"\[0, 3\] and \[2, 4\] overlap"),
    ],
)
def test_bad_config_is_named(cfg, match):
    with pytest.raises(ValueError, match=match):
        ColumnHistory(**cfg)


@pytest.mark.parametrize("kw, bad", [(dict(columns=(4, 9)), r"columns \[4, 9\]"), (dict(drop=[(5, 7)]), r"drop \[5, 7\]")])
def test_columns_outside_the_observation_are_named(kw, bad):
    with pytest.raises(ValueError, match=bad + r" outside agents.observation.*6 columns"):
        make_env(**kw).reset()


def test_agent_group_needs_batch_B_A():
    td = TensorDict(agents=TensorDict(observation=torch.zeros(N, D), batch_size=(N,)), batch_size=(N,))
    with pytest.raises(ValueError, match=r"agents.observation has shape \[4, 6\], expected \[4, A, 6\]"):
        ColumnHistory(COLS, L)(td)


@pytest.mark.parametrize("how", ["transform=", "append", "invert"])
def test_in_replay_buffer_is_refused(how):
    t = ColumnHistory(COLS, L, out_key=("agents", "h"))
    rb = ReplayBuffer(storage=LazyTensorStorage(8), batch_size=2, transform=t if how == "transform=" else None)
    if how != "transform=":
        rb.append_transform(t, invert=how == "invert")
    data = rollout(make_env(), 3).reshape(-1)
    with pytest.raises(RuntimeError, match="ColumnHistory cannot run in a replay buffer.*in the env"):
        rb.extend(data)
        rb.sample()


def test_after_observation_noise_holds_the_noisy_joints():
    noise = dict(fields={"q": (COLS, 0.5)}, generator_seed=0)
    env = make_env(episode_len=(2, 100, 100, 100), noise=noise)
    check_env_specs(env)
    out = rollout(env, 7)[OBS]
    assert torch.equal(history(out), expected_history(out))  # the noisy values seen
    clean = out[..., :1] + 100 * torch.arange(*COLS)
    assert (out[..., COLS[0] : COLS[1]] != clean).all()


def test_in_serial_env():
    make = functools.partial(CountingObsEnv, 2, (3, 100))
    t = ColumnHistory(COLS, L, drop=DROP)
    r = rollout(TransformedEnv(SerialEnv(2, make), t), 5)
    assert r[OBS].shape == (2, 2, 5, A, WIDTH) and t.history.shape == (2, 2, A, L, K)
    out = r[OBS].flatten(0, 1)
    assert torch.equal(history(out), expected_history(out))
