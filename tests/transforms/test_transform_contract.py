"""The TorchRL transform contract for every curriculum transform.

Each is run alone on an env, in a ``Compose`` (after ``StepCounter`` and
``StageTransition``), inside ``SerialEnv`` (transform outside and inside the workers),
inside ``ParallelEnv`` (slow), in a collector, without an env, and through a
``state_dict`` round trip; in a replay buffer each must refuse, and a per-robot entry
without the ``[*B, A]`` batch must be named. ``"stage"`` is ``StageTransition``; the others are reward
schedules (alone, they read the stage from an env that emits it).
"""
from __future__ import annotations

import functools

import pytest
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import ParallelEnv, SerialEnv, TransformedEnv
from torchrl.envs.utils import check_env_specs

from pnp.task.terms import REWARD_TERMS
from pnp.transforms import StageRewardSchedule, StageTransition

from ._toy_env import make_curriculum, make_pnp_toy_env, make_transformed

KINDS = ["stage", "dynamic", "fixed", "liu_max", "liu_min"]
SCHEDULES = KINDS[1:]
KEYS = [("next", "agents", "stage"), ("next", "agents", "episode_stage"), ("next", "agents", "reward")]


def rollout(env, steps=12):
    return env.rollout(steps, break_when_any_done=False)


def assert_same(a, b, keys=KEYS):
    for key in keys:
        if key in a.keys(True):
            assert torch.equal(a[key], b[key]), key


@pytest.mark.parametrize("kind", KINDS)
def test_alone_on_env(kind):
    env = make_transformed(kind, chain=False, emit_stage=kind != "stage")
    check_env_specs(env)
    r = rollout(env)
    assert r["next", "agents", "stage"].shape == (3, 12, 2, 1)


@pytest.mark.parametrize("kind", SCHEDULES)
def test_in_compose(kind):
    env = make_transformed(kind, chain=True)
    check_env_specs(env)
    r = rollout(env)
    # StepCounter truncates world 2 at step 5: its final stage is taken there too.
    done = r["next", "done"].squeeze(-1)
    ended = (r["next", "agents", "episode_stage"] >= 0).squeeze(-1).all(-1)
    assert torch.equal(done, ended) and done[2, 4]
    if kind == "dynamic":
        assert env.transform[-1].pop_stage_histogram().sum() == 2 * done.sum()


@pytest.mark.parametrize("kind", KINDS)
def test_serial_env_outside_and_inside(kind):
    mk = functools.partial(make_pnp_toy_env, emit_stage=kind != "stage")
    outside = TransformedEnv(SerialEnv(2, mk), make_curriculum(kind, chain=kind != "stage"))
    inside = SerialEnv(2, functools.partial(make_transformed, kind, kind != "stage", kind != "stage"))
    for env in (outside, inside):
        check_env_specs(env)
    a, b = rollout(outside), rollout(inside)
    assert a.shape == (2, 3, 12)
    assert_same(a, b)
    if kind == "dynamic":
        assert outside.transform[-1].rho.shape == (2, 3, 2, 12)


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["dynamic", "liu_max"])
def test_parallel_env(kind):
    make = functools.partial(make_transformed, kind, True)
    par = ParallelEnv(2, make)
    try:
        check_env_specs(par)
        assert_same(rollout(par), rollout(SerialEnv(2, make)))
    finally:
        par.close()


def test_collector_carries_the_stage():
    env = make_transformed("dynamic", chain=True)
    collector = Collector(env, policy=None, frames_per_batch=36, total_frames=72)
    batches = [b for b in collector]
    collector.shutdown()
    stage = torch.cat([b["next", "agents", "stage"] for b in batches], 1).squeeze(-1)  # [3, 24, 2]
    assert stage[2, :, 0].max() == 5  # climbs one step per env step: carried by the collector
    assert env.transform[-1].pop_stage_histogram().sum() > 0


def one_step() -> TensorDict:
    """t and ``"next"`` for 3 worlds of 2 robots, as an env step writes them."""
    nxt = {
        ("agents", "stage_conditions"): torch.ones(3, 2, 6, dtype=torch.bool),
        ("agents", "reward_terms"): torch.ones(3, 2, len(REWARD_TERMS)),
        ("agents", "stage"): torch.full((3, 2, 1), 4),
        ("agents", "episode_stage"): torch.full((3, 2, 1), -1),
        "done": torch.zeros(3, 1, dtype=torch.bool),
    }
    return TensorDict({("agents", "stage"): torch.full((3, 2, 1), 3), "next": TensorDict(nxt, [3])}, [3])


@pytest.mark.parametrize("kind", KINDS)
def test_without_env(kind):
    t = make_curriculum(kind)
    out = t(one_step())
    if isinstance(t, StageTransition):
        assert (out["next", "agents", "stage"] == 4).all()
    else:
        assert isinstance(t, StageRewardSchedule)
        assert out["next", "agents", "reward"].shape == (3, 2, 1)


@pytest.mark.parametrize("how", ["transform=", "append_transform", "invert"])
@pytest.mark.parametrize("kind", KINDS)
def test_in_replay_buffer_is_refused(kind, how):
    # Its state (and the stage) is per env world; sampled rows have no world identity.
    t = make_curriculum(kind)
    rb = ReplayBuffer(storage=LazyTensorStorage(8), batch_size=2, transform=t if how == "transform=" else None)
    if how != "transform=":
        rb.append_transform(t, invert=how == "invert")
    with pytest.raises(RuntimeError, match="cannot run in a replay buffer.*no world identity.*in the env"):
        rb.extend(one_step())  # the inverted transform runs here
        rb.sample()


@pytest.mark.parametrize("bad_shape", [(3, 1), (3, 4, 1)], ids=["no_agent_dim", "wrong_agent_count"])
@pytest.mark.parametrize("kind", KINDS)
def test_agent_entries_need_batch_B_A(kind, bad_shape):
    td = one_step()
    key = ("agents", "stage") if kind == "stage" else ("next", "agents", "stage")  # what each reads
    td.get(key[:-1]).set(key[-1], torch.zeros(bad_shape, dtype=torch.long))
    expected = rf"agents.stage has shape \[{', '.join(map(str, bad_shape))}\], expected \[3, 2, 1\]"
    with pytest.raises(ValueError, match=expected + r".*'agents' group must have batch \[\*B, A\]"):
        make_curriculum(kind)(td)


@pytest.mark.parametrize("kind", KINDS)
def test_state_dict_round_trip(kind):
    trained = make_transformed(kind, chain=True)
    rollout(trained, 23)
    fresh = make_transformed(kind, chain=True)
    state = trained.transform.state_dict()
    fresh.transform.load_state_dict(state)
    if kind == "stage":
        assert not state  # stateless: the stage lives in the tensordict
    for key, value in state.items():
        assert torch.equal(value, fresh.transform.state_dict()[key]), key
    assert_same(rollout(trained), rollout(fresh))
    for key, value in trained.transform.state_dict().items():
        assert torch.equal(value, fresh.transform.state_dict()[key]), key


@pytest.mark.parametrize("kind", KINDS)
def test_clone(kind):
    # A clone of a fresh transform acts as a fresh one does on the same env...
    reference = rollout(TransformedEnv(make_pnp_toy_env(), make_curriculum(kind, chain=True)))
    t = make_curriculum(kind, chain=True)
    assert_same(rollout(TransformedEnv(make_pnp_toy_env(), t.clone())), reference)
    # ...and a clone of a used one carries its state but never writes back into it.
    used = TransformedEnv(make_pnp_toy_env(), t)
    rollout(used, 7)
    before = {k: v.clone() for k, v in t.state_dict().items()}
    copy = t.clone()
    assert before.keys() == copy.state_dict().keys()
    assert all(torch.equal(before[k], v) for k, v in copy.state_dict().items())
    rollout(TransformedEnv(make_pnp_toy_env(), copy), 9)
    assert all(torch.equal(before[k], v) for k, v in t.state_dict().items())
    if kind != "stage":  # the schedules keep their scales as state: the check above is not vacuous
        assert before and any(not torch.equal(before[k], v) for k, v in copy.state_dict().items())
