"""recipes/analyze/falls.py: the hook's per-fall window, and the script on a tiny two-robot checkpoint."""
from __future__ import annotations

import json

import torch
from tensordict import TensorDict

from pnp.analysis import falls
from pnp.task import OBS_FIELDS
from pnp.task.terms import CONDITIONS, REWARD_TERMS
from tests.training._tiny import tiny_train

_CMD, _VEL = OBS_FIELDS["ego"]["last_action"].start, OBS_FIELDS["ego"]["base_vel"].start


def _step(vx: list[list[float]], fell: list[list[bool]], held: list[list[bool]], spacing: list[float]) -> TensorDict:
    """Worlds x two robots: commanded vx (measured velocity zero), fallen, holding; the robots' spacing."""
    n, r = len(vx), 2
    ego = torch.zeros(n, r, 31)
    ego[..., _CMD] = torch.tensor(vx)
    terms = torch.zeros(n, r, len(REWARD_TERMS))
    terms[..., REWARD_TERMS.index("fall")] = torch.tensor(fell, dtype=torch.float)
    cond = torch.zeros(n, r, len(CONDITIONS), dtype=torch.bool)
    cond[..., CONDITIONS.index("object_grabbed")] = torch.tensor(held)
    partner = torch.zeros(n, r, 10)
    partner[..., 0] = torch.tensor(spacing)[:, None]
    agents = TensorDict({"ego": ego, "reward_terms": terms, "stage_conditions": cond, "neighbour": partner,
                         "stage": torch.full((n, r, 1), 3)}, batch_size=(n, r))
    return TensorDict({"agents": agents}, batch_size=(n,))


def test_a_fall_keeps_the_fallen_robots_last_window_and_reset_forgets_it():
    hook = falls.Falls(2, window=2)
    steps = [([[0.1, 0.0], [0.2, 0.2]], [[False, False], [False, False]], 1.0),
             ([[0.9, 0.0], [0.2, 0.2]], [[False, False], [False, False]], 1.5),
             ([[0.3, 0.0], [0.2, 0.2]], [[False, True], [False, False]], 1.2)]
    for vx, fell, spacing in steps:
        hook.after_step(None, _step(vx, fell, [[True, True], [False, False]], [spacing, 1.0]))
    rec = hook.record(0)
    # Robot 1 fell: its commands over the last two steps were 0, so the maxima are 0, not robot 0's 0.9.
    assert rec["fell_robots"] == [1] and rec["held_per_robot"] == [True, True] and rec["stage_per_robot"] == [3, 3]
    assert rec["speed_max"] == 0.0 and abs(rec["spacing_change"] - 0.3) < 1e-6
    assert hook.record(1) == {"fell_robots": [], "stage_per_robot": [3, 3], "held_per_robot": [False, False]}
    hook.reset(torch.tensor([True, False]))
    hook.after_step(None, _step([[0.5, 0.5], [0.2, 0.2]], [[True, False], [False, False]],
                                [[False, False], [False, False]], [2.0, 1.0]))
    rec = hook.record(0)  # only the new episode's one step: no spacing change from the last episode
    assert rec["fell_robots"] == [0] and rec["speed_max"] == 0.5 and rec["spacing_change"] == 0.0
    ref = hook.reference()
    assert ref["carrying"]["robot_steps"] == 6 and ref["not_carrying"]["robot_steps"] == 3 * 2 + 4


def test_falls_script_writes_its_summary(tmp_path):
    tiny_train(tmp_path / "run", "total_iterations=1", "task=dual_pnp")
    out = falls.main([f"checkpoint={tmp_path / 'run'}/checkpoint.pt", f"out={tmp_path / 'f.json'}",
                      "trials=3", "env.num_worlds=3", "env.max_episode_steps=5"])
    assert json.loads((tmp_path / "f.json").read_text()) == json.loads(json.dumps(out))
    assert out["trials"] == 3 and out["falls"] == len(out["fall_trials"]) == out["failure_causes"]["fall"]
    assert sum(out["falls_by_stage"].values()) <= out["falls"]
    assert out["everywhere"]["carrying"]["robot_steps"] + out["everywhere"]["not_carrying"]["robot_steps"] >= 3 * 2
    assert out["commit"] and out["machine"]
