from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import TransformedEnv

from pnp.task.stage_graph import pnp_default_stage_graph
from pnp.transforms import StageTransition

from ._toy_env import ToyStageEnv

ONE_HOT = ("agents", "stage_one_hot")


def make_env(**kw) -> TransformedEnv:
    return TransformedEnv(ToyStageEnv(**kw), StageTransition(pnp_default_stage_graph(), one_hot_key=ONE_HOT))


def stages(rollout, key=("next", "agents", "stage")):
    return rollout[key].squeeze(-1)  # [N, T, A]


def test_reset_writes_stage_zero_and_no_episode_end():
    td = make_env().reset()
    assert td["agents", "stage"].shape == (3, 2, 1) and td["agents", "stage"].dtype == torch.long
    assert (td["agents", "stage"] == 0).all()
    assert (td["agents", "episode_stage"] == -1).all()
    assert td[ONE_HOT].shape == (3, 2, 7) and (td[ONE_HOT][..., 0] == 1).all()


def test_stage_climbs_to_reach_one_step_at_a_time():
    reach = torch.tensor([[0, 3], [6, 1], [2, 5]])
    r = make_env(reach=reach, episode_len=10).rollout(8)
    s = stages(r)
    expected = torch.minimum(torch.arange(1, 9)[None, :, None], reach[:, None, :])
    assert torch.equal(s, expected)
    one_hot = r[("next", *ONE_HOT)]
    assert torch.equal(one_hot.argmax(-1), s) and torch.equal(one_hot.sum(-1), torch.ones_like(s).float())


def test_episode_stage_recorded_at_done_only():
    reach = torch.tensor([[0, 3], [6, 1], [2, 5]])
    r = make_env(reach=reach, episode_len=[4, 5, 6]).rollout(6, break_when_any_done=False)
    ep = stages(r, ("next", "agents", "episode_stage"))
    done = r["next", "done"].squeeze(-1)  # [N, T]
    assert torch.equal(ep[done], stages(r)[done])
    assert (ep[~done] == -1).all()
    assert ep[0, 3].tolist() == [0, 3] and ep[1, 4].tolist() == [5, 1] and ep[2, 5].tolist() == [2, 5]


def test_backward_edges_when_conditions_are_lost():
    # Climb for 5 steps, then every condition is lost.
    reach = torch.tensor([[1, 2], [6, 5], [3, 4]])
    r = make_env(reach=reach, episode_len=20, lose_after=5).rollout(8)
    s = stages(r)
    at5, after = s[:, 4], s[:, 5]
    assert at5.tolist() == [[1, 2], [5, 5], [3, 4]]
    # S1, S2 -> S0 (pickup), S5 -> S4 (release); S3, S4 have no backward edge.
    assert after.tolist() == [[0, 0], [4, 4], [3, 4]]
    assert s[1, 6].tolist() == [4, 4]  # one edge per step, no cascade past S4


def test_peak_episode_stage_is_the_highest_reached():
    # Climb for 5 steps, lose every condition, episode ends at step 8: final != peak.
    reach = torch.tensor([[1, 2], [6, 5], [3, 4]])
    kw = dict(reach=reach, episode_len=8, lose_after=5)
    final = TransformedEnv(ToyStageEnv(**kw), StageTransition(pnp_default_stage_graph())).rollout(8)
    env = TransformedEnv(ToyStageEnv(**kw), StageTransition(pnp_default_stage_graph(), episode_stage="peak"))
    peak = env.rollout(8, break_when_any_done=False)
    assert stages(final, ("next", "agents", "episode_stage"))[:, -1].tolist() == [[0, 0], [4, 4], [3, 4]]
    assert stages(peak, ("next", "agents", "episode_stage"))[:, -1].tolist() == [[1, 2], [5, 5], [3, 4]]
    # The peak restarts from 0 after the reset; the stage itself is unchanged by the option.
    assert torch.equal(stages(peak)[:, :8], stages(final)[:, :8])
    td = env.reset()
    assert (td["agents", "stage_peak"] == 0).all()


def test_unknown_episode_stage_reading_is_named():
    with pytest.raises(ValueError, match="episode_stage must be 'final' or 'peak', got 'max'"):
        StageTransition(pnp_default_stage_graph(), episode_stage="max")


def test_partial_reset_keeps_other_worlds_stage():
    reach = torch.tensor([[6, 6], [6, 6], [6, 6]])
    r = make_env(reach=reach, episode_len=[2, 5, 5]).rollout(4, break_when_any_done=False)
    # World 0 is reset after step 2, worlds 1 and 2 keep climbing.
    assert stages(r)[0, :, 0].tolist() == [1, 2, 1, 2]
    assert stages(r)[1, :, 0].tolist() == [1, 2, 3, 4]
    assert (r["agents", "stage"][0, 2] == 0).all()  # root of the step after the reset


def test_reset_keeps_stage_of_worlds_not_reset():
    t = StageTransition(pnp_default_stage_graph())
    prev = TensorDict({("agents", "stage"): torch.tensor([[[3], [4]], [[5], [6]]]), "_reset": torch.tensor([[True], [False]])}, [2])
    out = t._reset(prev, TensorDict({}, [2]))
    assert out["agents", "stage"].squeeze(-1).tolist() == [[0, 0], [5, 6]]


def test_per_agent_done_key_and_env_free_call():
    t = StageTransition(pnp_default_stage_graph(), done_key=("agents", "done"))
    cond = torch.ones(2, 2, 6, dtype=torch.bool)
    td = TensorDict(
        {
            ("agents", "stage"): torch.tensor([[[0], [5]], [[6], [2]]]),
            ("next", "agents", "stage_conditions"): cond,
            ("next", "agents", "done"): torch.tensor([[[True], [False]], [[False], [True]]]),
        },
        [2],
    )
    out = t(td)
    assert out["next", "agents", "stage"].squeeze(-1).tolist() == [[1, 6], [6, 3]]
    assert out["next", "agents", "episode_stage"].squeeze(-1).tolist() == [[1, -1], [-1, 3]]


def test_missing_conditions_key_names_it():
    t = StageTransition(pnp_default_stage_graph())
    td = TensorDict({("agents", "stage"): torch.zeros(2, 2, 1, dtype=torch.long), ("next", "agents", "x"): torch.zeros(2, 2)}, [2])
    with pytest.raises(KeyError, match=r"agents.stage_conditions not found.*keys present: agents.x"):
        t(td)


def test_missing_stage_at_step_input():
    t = StageTransition(pnp_default_stage_graph())
    td = TensorDict({("next", "agents", "stage_conditions"): torch.zeros(2, 2, 6, dtype=torch.bool), ("next", "done"): torch.zeros(2, 1, dtype=torch.bool)}, [2])
    with pytest.raises(KeyError, match="reset the env first"):
        t(td)


def test_condition_count_mismatch():
    with pytest.raises(ValueError, match="5 columns"):
        make_env(n_conditions=5).reset()
