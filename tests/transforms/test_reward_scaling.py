"""Hand-computed checks of the schedules, driven without an env (one td per step).

Config: stages 0..2; terms a (S0, mu 2), b (S1, mu 8), c (S2, mu 4), f (fixed, -1);
K = 2, mu_min = 0.5, so the initial rho is (2, 0.5, 0.5).
"""
from __future__ import annotations

import io

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from tensordict import TensorDict
from torchrl.envs import Compose, TransformedEnv

from pnp.task.stage_graph import StageGraph, pnp_default_reward_config
from pnp.task.terms import REWARD_TERMS
from pnp.transforms import (
    AdaptiveRewardScaling,
    FixedScales,
    LiuMax,
    LiuMin,
    StageTransition,
    make_reward_schedule,
)

from ._toy_env import ToyStageEnv

CFG = dict(
    term_names=("a", "b", "c", "f"),
    term_stage={"a": 0, "b": 1, "c": 2},
    mu={"a": 2.0, "b": 8.0, "c": 4.0},
    fixed_weights={"f": -1.0},
)
DYN = dict(CFG, K=2.0, mu_min=0.5)
LOW = {"a": 0.0, "b": -1.0, "c": 0.0}
HIGH = {"a": 1.0, "b": 0.5, "c": 3.0}


def step(t, stage, final=None, terms=None):
    """One env-free step of a [W, A] batch; returns the reward [W, A]."""
    stage = torch.as_tensor(stage)
    final = torch.full_like(stage, -1) if final is None else torch.as_tensor(final)
    terms = torch.ones(4) if terms is None else torch.as_tensor(terms)
    terms = terms.expand(*stage.shape, terms.shape[-1])
    nxt = {("agents", "reward_terms"): terms, ("agents", "stage"): stage[..., None], ("agents", "episode_stage"): final[..., None]}
    td = TensorDict({"next": TensorDict(nxt, stage.shape[:1])}, stage.shape[:1])
    return t(td)["next", "agents", "reward"].squeeze(-1)


def reset(t, mask):
    mask = torch.as_tensor(mask)
    t._reset(TensorDict({"_reset": mask[:, None]}, mask.shape), TensorDict({}, mask.shape))


def episode(t, final, mask=None):
    """An episode of every slot ending in ``final`` [W, A], then a reset of ``mask``."""
    final = torch.as_tensor(final)
    step(t, final, final)
    reset(t, torch.ones(final.shape[0], dtype=torch.bool) if mask is None else mask)


def rho(t):
    return t.rho[0, 0].tolist()


def test_initial_scales_and_reward():
    t = AdaptiveRewardScaling(**DYN)
    r = step(t, [[0]])
    assert rho(t) == [2.0, 0.5, 0.5]
    assert r.item() == pytest.approx(2 + 0.5 + 0.5 - 1)


def test_hand_computed_update_sequence():
    t = AdaptiveRewardScaling(**DYN)
    expected = [
        (1, [1.0, 1.0, 0.5]),
        (1, [0.5, 2.0, 0.5]),  # a floors at mu_min
        (1, [0.5, 4.0, 0.5]),
        (1, [0.5, 8.0, 0.5]),
        (1, [0.5, 8.0, 0.5]),  # b capped at mu_b
        (2, [0.5, 4.0, 1.0]),
        (0, [1.0, 2.0, 0.5]),
    ]
    for final, want in expected:
        episode(t, [[final]])
        assert rho(t) == want
    assert step(t, [[2]]).item() == pytest.approx(1 + 2 + 0.5 - 1)


def test_completed_floor_keeps_a_share_of_mu_below_lambda_only():
    t = AdaptiveRewardScaling(**DYN, completed_floor=0.75)
    expected = [
        (1, [1.5, 1.0, 0.5]),  # a (stage 0 < 1): max(2/2, 0.75 * 2)
        (1, [1.5, 2.0, 0.5]),
        (2, [1.5, 6.0, 1.0]),  # b completed now: max(2/2, 0.75 * 8)
        (0, [2.0, 3.0, 0.5]),  # lambda = 0: nothing lies below it, Eq. 2 as is
    ]
    for final, want in expected:
        episode(t, [[final]])
        assert rho(t) == want
    with pytest.raises(ValueError, match="1.5"):
        AdaptiveRewardScaling(**DYN, completed_floor=1.5)


def test_enter_final_fixes_every_slot_at_mu():
    t = AdaptiveRewardScaling(**DYN)
    with pytest.raises(RuntimeError, match="first reset"):
        t.enter_final()
    step(t, [[0], [1]])
    t.enter_final()
    assert t.in_final.all() and t.rho.tolist() == [[[2.0, 8.0, 4.0]], [[2.0, 8.0, 4.0]]]
    episode(t, [[0], [2]])  # later episodes change nothing, as in the paper's final stage
    assert t.rho.tolist() == [[[2.0, 8.0, 4.0]], [[2.0, 8.0, 4.0]]]


def test_rho_constant_within_an_episode():
    t = AdaptiveRewardScaling(**DYN)
    episode(t, [[1]])
    before = t.rho.clone()
    rewards = [step(t, [[s]]).item() for s in (0, 1, 2, 1, 0)]
    assert torch.equal(t.rho, before) and len(set(rewards)) == 1


def test_only_reset_worlds_are_updated():
    t = AdaptiveRewardScaling(**DYN)
    step(t, [[1], [2]], final=[[1], [2]])  # both worlds end their episode
    reset(t, [True, False])
    assert t.rho[0, 0].tolist() == [1.0, 1.0, 0.5] and t.rho[1, 0].tolist() == [2.0, 0.5, 0.5]
    reset(t, [False, True])  # world 1's pending end stage (S2) is applied at its reset
    assert t.rho[0, 0].tolist() == [1.0, 1.0, 0.5] and t.rho[1, 0].tolist() == [1.0, 0.5, 1.0]


def test_per_agent_reset_key():
    t = AdaptiveRewardScaling(**DYN, reset_keys=[("agents", "_reset")])
    step(t, [[1, 1]], final=[[1, 1]])
    agents = TensorDict({"_reset": torch.tensor([[[False], [True]]])}, [1, 2])
    t._reset(TensorDict({"agents": agents}, [1]), TensorDict({}, [1]))
    assert t.rho[0, 0].tolist() == [2.0, 0.5, 0.5] and t.rho[0, 1].tolist() == [1.0, 1.0, 0.5]
    assert t.pending_stage.tolist() == [[1, -1]]


def test_first_reset_and_resets_without_episode_end_change_nothing():
    t = AdaptiveRewardScaling(**DYN)
    reset(t, [True])  # fresh: nothing to update, nothing allocated
    assert not t.initialized
    step(t, [[2]])
    reset(t, [True])  # episode cut short, no done seen
    assert rho(t) == [2.0, 0.5, 0.5]


def test_agents_have_their_own_scales():
    t = AdaptiveRewardScaling(**DYN)
    episode(t, [[1, 2]])
    assert t.rho[0, 0].tolist() == [1.0, 1.0, 0.5] and t.rho[0, 1].tolist() == [1.0, 0.5, 1.0]


def test_final_stage_after_exactly_five_consecutive_last_stage_episodes():
    t = AdaptiveRewardScaling(**DYN)
    for i in range(4):
        episode(t, [[2]])
    assert not t.in_final.any() and t.final_streak.item() == 4
    assert rho(t) == [0.5, 0.5, 4.0]
    episode(t, [[2]])
    assert t.in_final.all() and rho(t) == [2.0, 8.0, 4.0]
    episode(t, [[0]])  # fixed for good
    assert t.in_final.all() and rho(t) == [2.0, 8.0, 4.0]


def test_interrupted_run_does_not_enter_final_stage():
    t = AdaptiveRewardScaling(**DYN)
    for final in [2, 2, 2, 2, 1, 2, 2, 2, 2]:
        episode(t, [[final]])
    assert not t.in_final.any() and t.final_streak.item() == 4
    episode(t, [[2]])
    assert t.in_final.all()


def test_pnp_table_enters_final_stage_after_five_s6_episodes():
    t = make_reward_schedule("dynamic", K=2.0, mu_min=0.1, **pnp_default_reward_config())
    terms = torch.ones(len(REWARD_TERMS))
    for i in range(5):
        step(t, [[6]], [[6]], terms=terms)
        reset(t, [True])
        assert bool(t.in_final.all()) == (i == 4)
    assert t.rho_by_term() == pytest.approx(t.mu)


def test_stage_histogram_counts_and_clears():
    t = AdaptiveRewardScaling(**DYN)
    step(t, [[0, 1], [2, 2]], final=[[0, -1], [2, 2]])
    step(t, [[1, 1], [0, 0]], final=[[-1, 1], [-1, -1]])
    assert t.pop_stage_histogram().tolist() == [1, 1, 2]
    assert t.pop_stage_histogram().tolist() == [0, 0, 0]


def test_stage_progress_and_gates():
    cfg = dict(term_names=("p", "g", "f"), term_stage={"p": 2, "g": 1}, mu={"p": 1.0, "g": 1.0},
               fixed_weights={"f": 0.0}, stage_progress_term="p", stage_gates={"g": 2})
    t = FixedScales(**cfg)
    td = lambda s: TensorDict({"next": TensorDict({("agents", "reward_terms"): torch.ones(1, 1, 3) * 5,
                                                   ("agents", "stage"): torch.tensor([[[s]]]),
                                                   ("agents", "episode_stage"): torch.tensor([[[-1]]])}, [1])}, [1])
    assert t(td(1))["next", "agents", "reward"].item() == 1.0  # progress = stage, g gated off
    assert t(td(2))["next", "agents", "reward"].item() == 2.0 + 5.0


@pytest.mark.parametrize(
    "cls, extra, want",
    [(FixedScales, {}, [2 * 0.5 + 8 * 0.25 + 4 * 2 - 1] * 3),
     (LiuMax, {"high": HIGH}, [1 - 1, 2 * 1 + 2 - 1, 2 * 1 + 8 * 0.5 + 8 - 1]),
     (LiuMin, {"low": LOW}, [1 - 1, 0 + 2 - 1, 0 + 8 * -1 + 8 - 1])],
)
def test_fixed_and_liu_schedules(cls, extra, want):
    t = cls(**CFG, **extra)
    got = [step(t, [[s]], terms=torch.tensor([0.5, 0.25, 2.0, 1.0])).item() for s in (0, 1, 2)]
    assert got == pytest.approx(want)


def test_make_reward_schedule_switch():
    cfg = dict(DYN, low=LOW, high=HIGH, final_after=3)
    kinds = {"dynamic": AdaptiveRewardScaling, "fixed": FixedScales, "liu_max": LiuMax, "liu_min": LiuMin}
    for name, cls in kinds.items():
        assert type(make_reward_schedule(name, **cfg)) is cls
    assert make_reward_schedule("dynamic", **cfg).final_after == 3
    with pytest.raises(ValueError, match="unknown reward schedule 'nope'"):
        make_reward_schedule("nope", **cfg)
    with pytest.raises(TypeError):
        make_reward_schedule("fixed", typo=1, **CFG)


@pytest.mark.parametrize(
    "change, match",
    [
        (dict(K=1.0), "K must be > 1"),
        (dict(mu_min=0.0), "mu_min must be > 0"),
        (dict(mu_min=3.0), "exceeds mu_j of \\['a'\\]"),
        (dict(term_stage={"a": 0, "b": 1, "zz": 2}), "unknown term.*'zz'"),
        (dict(mu={"a": 2.0, "b": 8.0}), "missing \\['c'\\]"),
        (dict(fixed_weights={}), "missing \\['f'\\]"),
        (dict(mu={"a": 2.0, "b": -8.0, "c": 4.0}), "mu\\['b'\\] must be > 0"),
        (dict(term_stage={"a": 0, "b": 1, "c": 9}, n_stages=3), "not in \\[0, 3\\)"),
        (dict(stage_gates={"q": 1}), "unknown term.*'q'"),
        (dict(term_names=("a", "b", "c", "c")), "duplicate"),
        (dict(final_after=0), "final_after"),
    ],
)
def test_bad_config(change, match):
    with pytest.raises(ValueError, match=match):
        AdaptiveRewardScaling(**dict(DYN, **change))


def test_liu_needs_finite_bounds():
    with pytest.raises(ValueError, match="finite.*'c'"):
        LiuMax(**CFG, high=dict(HIGH, c=float("inf")))
    with pytest.raises(ValueError, match="missing \\['b'\\]"):
        LiuMin(**CFG, low={"a": 0.0, "c": 0.0})


def test_bad_step_input():
    t = AdaptiveRewardScaling(**DYN)
    with pytest.raises(ValueError, match="3 terms in its last dim"):
        step(t, [[0]], terms=torch.ones(3))
    td = TensorDict({"next": TensorDict({("agents", "stage"): torch.zeros(1, 1, 1, dtype=torch.long)}, [1])}, [1])
    with pytest.raises(KeyError, match="agents.reward_terms not found.*keys present: agents.stage"):
        t(td)


def test_state_dict_round_trip_continues_identically():
    a = AdaptiveRewardScaling(**DYN)
    for final in [1, 2, 2, 2]:
        episode(a, [[final, 0], [2, 1]])
    step(a, [[2, 0], [1, 1]], final=[[2, -1], [-1, -1]])  # one end pending, not yet reset
    buf = io.BytesIO()
    torch.save(a.state_dict(), buf)
    b = AdaptiveRewardScaling(**DYN)
    b.load_state_dict(torch.load(io.BytesIO(buf.getvalue())))
    assert set(a.state_dict()) == {"rho", "final_streak", "in_final", "pending_stage", "stage_histogram"}
    for t in (a, b):
        reset(t, [True, True])
        for final in [2, 2, 0]:
            episode(t, [[final, 2], [2, 2]])
    for key, value in a.state_dict().items():
        assert torch.equal(value, b.state_dict()[key]), key
    assert a.in_final[0, 0] and not a.in_final[0, 1]


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.lists(st.integers(-1, 2), min_size=4, max_size=4), st.lists(st.booleans(), min_size=2, max_size=2)), max_size=30))
def test_rho_stays_within_bounds(events):
    t = AdaptiveRewardScaling(**dict(DYN, final_after=3))
    step(t, [[0, 0], [0, 0]])
    mu = t._mu
    was_final = t.in_final.clone()
    for final, mask in events:
        final = torch.tensor(final).reshape(2, 2)
        before = t.rho.clone()
        step(t, final.clamp(min=0), final)
        assert torch.equal(t.rho, before)  # never changes within an episode
        reset(t, mask)
        assert (t.rho >= 0.5).all() and (t.rho <= mu).all()
        assert (t.rho[t.in_final] == mu).all()
        assert (t.in_final | ~was_final).all()  # final is for good
        not_reset = ~torch.tensor(mask)
        assert torch.equal(t.rho[not_reset], before[not_reset])
        was_final = t.in_final.clone()


def test_in_env_rho_follows_each_slots_episodes():
    graph = StageGraph(("s0", "s1", "s2"), ("c0", "c1"))
    env = ToyStageEnv(n_worlds=2, n_agents=2, n_conditions=2, reach=torch.tensor([[0, 1], [2, 2]]), episode_len=3)
    env = TransformedEnv(env, Compose(StageTransition(graph), AdaptiveRewardScaling(**DYN)))
    env.reset()  # a fresh env's first reset sizes the state and updates nothing
    assert env.transform[1].rho.tolist() == [[[2.0, 0.5, 0.5]] * 2] * 2
    # Two episodes per world; rollout resets after every step but its last, so 7 steps.
    env.rollout(7, break_when_any_done=False)
    t = env.transform[1]
    assert t.rho[0, 0].tolist() == [2.0, 0.5, 0.5]  # S0 twice: stays at (mu_a, mu_min, mu_min)
    assert t.rho[0, 1].tolist() == [0.5, 2.0, 0.5]
    assert t.rho[1, 0].tolist() == [0.5, 0.5, 2.0] == t.rho[1, 1].tolist()
    assert t.pop_stage_histogram().tolist() == [2, 2, 4] and (t.pending_stage == -1).all()
