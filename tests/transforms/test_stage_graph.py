from __future__ import annotations

import dataclasses

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from pnp.task.stage_graph import StageGraph, pnp_default_reward_config, pnp_default_stage_graph
from pnp.task.terms import CONDITIONS, REWARD_TERMS, STAGES

ALL, NONE = torch.ones(7, 6, dtype=torch.bool), torch.zeros(7, 6, dtype=torch.bool)


def small(**kw) -> StageGraph:
    args = dict(stages=("a", "b", "c"), conditions=("ab", "bc"))
    args.update(kw)
    return StageGraph(**args)


def test_pnp_default_graph():
    g = pnp_default_stage_graph()
    assert g.stages == STAGES and g.conditions == CONDITIONS
    assert g.backward_edges == ((1, 0), (2, 0), (5, 4), (6, 5))
    assert g.n_stages == 7 and g.last_stage == 6
    with pytest.raises(dataclasses.FrozenInstanceError):
        g.stages = ()


def test_forward_one_stage_at_most():
    g = pnp_default_stage_graph()
    assert g.next_stage(torch.arange(7), ALL).tolist() == [1, 2, 3, 4, 5, 6, 6]


def test_forward_needs_own_condition_only():
    g = pnp_default_stage_graph()
    cond = torch.zeros(6, dtype=torch.bool)
    cond[3] = True  # "object_on_goal" alone moves S3 -> S4 only
    stage = torch.arange(7)
    out = g.next_stage(stage, cond.expand(7, 6))
    assert out[3] == 4
    # S4 lost its entry condition? No: conditions[3] holds, so it stays.
    assert out[4] == 4


def test_backward_edges_honoured_and_others_refused():
    g = pnp_default_stage_graph()
    # Every condition lost: S1, S2 -> S0; S5 -> S4; S6 -> S5; S3, S4 have no edge.
    assert g.next_stage(torch.arange(7), NONE).tolist() == [0, 0, 0, 3, 4, 4, 5]


def test_forward_wins_over_backward():
    g = pnp_default_stage_graph()
    cond = torch.zeros(6, dtype=torch.bool)
    cond[1] = True  # S1's entry condition (gripper_ready) lost, its forward one holds
    assert g.next_stage(torch.tensor(1), cond) == 2


def test_batched_shapes():
    g = pnp_default_stage_graph()
    stage = torch.randint(0, 7, (2, 3, 4))
    cond = torch.rand(2, 3, 4, 6) > 0.5
    out = g.next_stage(stage, cond)
    assert out.shape == stage.shape and out.dtype == torch.long
    flat = g.next_stage(stage.reshape(-1), cond.reshape(-1, 6))
    assert torch.equal(out.reshape(-1), flat)


def test_stage_names_or_indices_for_edges():
    assert small(backward_edges=[("c", "a")]) == small(backward_edges=[(2, 0)])


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(conditions=("ab",)), "expected 2 conditions"),
        (dict(stages=("a", "b", "a")), "duplicate stage"),
        (dict(conditions=("x", "x")), "duplicate condition"),
        (dict(backward_edges=[(0, 2)]), "goes forward"),
        (dict(backward_edges=[(1, 1)]), "self-loop"),
        (dict(backward_edges=[(2, 0), (2, 1)]), "more than one backward edge"),
        (dict(backward_edges=[("c", "z")]), "unknown stage 'z'"),
        (dict(backward_edges=[(5, 0)]), "out of range"),
        (dict(forward_edges=[(0, 1), (1, 2), (2, 1)]), "forward cycle"),
        (dict(forward_edges=[(0, 1)]), "unreachable stage"),
        (dict(forward_edges=[(0, 2), (2, 1)]), "chain"),
        (dict(stages=(), conditions=()), "at least one stage"),
    ],
)
def test_invalid_graphs(kw, match):
    with pytest.raises(ValueError, match=match):
        small(**kw)


def test_forward_edges_spelled_out():
    assert small(forward_edges=[(0, 1), ("b", "c")]).forward_edges == ((0, 1), (1, 2))


def test_condition_count_mismatch_at_step():
    with pytest.raises(ValueError, match="columns"):
        pnp_default_stage_graph().next_stage(torch.zeros(2, dtype=torch.long), torch.ones(2, 5, dtype=torch.bool))


def _reference(g: StageGraph, s: int, cond: list[bool]) -> int:
    if s < g.last_stage and cond[s]:
        return s + 1
    back = dict(g.backward_edges)
    if s > 0 and not cond[s - 1] and s in back:
        return back[s]
    return s


@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(1, 8),
    data=st.data(),
)
def test_next_stage_matches_reference(n, data):
    back = data.draw(st.lists(st.integers(1, max(n - 1, 1)), unique=True).filter(lambda v: n > 1 or not v))
    edges = [(a, data.draw(st.integers(0, a - 1))) for a in back]
    g = StageGraph(tuple(f"s{i}" for i in range(n)), tuple(f"c{i}" for i in range(n - 1)), edges)
    stage = data.draw(st.lists(st.integers(0, n - 1), min_size=1, max_size=16))
    cond = [data.draw(st.lists(st.booleans(), min_size=n - 1, max_size=n - 1)) for _ in stage]
    out = g.next_stage(torch.tensor(stage), torch.tensor(cond, dtype=torch.bool).reshape(len(stage), n - 1))
    for s, c, o in zip(stage, cond, out.tolist()):
        assert o == _reference(g, s, c)
        assert o <= s + 1  # never more than one stage forward
        assert o in (s, s + 1) or (s, o) in g.backward_edges  # backward only along edges


def test_pnp_default_reward_config_matches_terms():
    cfg = pnp_default_reward_config()
    assert cfg["term_names"] == REWARD_TERMS
    assert set(cfg["mu"]) | set(cfg["fixed_weights"]) == set(REWARD_TERMS)
    assert cfg["n_stages"] == 7 and cfg["stage_progress_term"] in REWARD_TERMS
