"""CarryStrain measures the change of the gripper distance over the two-robot carry only."""
from __future__ import annotations

from types import SimpleNamespace

import torch
from tensordict import TensorDict

from pnp.deploy.carry import CarryStrain, carry_summary
from pnp.task.terms import CONDITIONS

GRABBED, LIFTED = CONDITIONS.index("object_grabbed"), CONDITIONS.index("object_lifted")


def _step(hook, gap: float, grabbed: bool, done: bool = False):
    ee = torch.tensor([[[0.0, 0.0, 0.5], [gap, 0.0, 0.5]]])
    env = SimpleNamespace(base_env=SimpleNamespace(physical_state=lambda: SimpleNamespace(ee_pos=ee)))
    cond = torch.zeros(1, 2, len(CONDITIONS), dtype=torch.bool)
    cond[..., GRABBED] = grabbed
    cond[..., LIFTED] = grabbed
    nxt = TensorDict({("agents", "stage_conditions"): cond, "done": torch.tensor([[done]])}, batch_size=[1])
    hook.after_step(env, nxt)


def test_change_is_measured_from_the_carry_start_and_only_while_carrying():
    hook = CarryStrain(1)
    _step(hook, 2.0, grabbed=False)  # approaching: not counted
    _step(hook, 1.0, grabbed=True)   # the carry begins at 1.0 m
    _step(hook, 1.1, grabbed=True)
    _step(hook, 0.8, grabbed=True)
    _step(hook, 3.0, grabbed=False)  # released: not counted
    r = hook.record(0)
    assert r["carry_steps"] == 3
    assert abs(r["grip_distance_change_max_m"] - 0.2) < 1e-6
    assert abs(r["grip_distance_change_mean_m"] - 0.1) < 1e-6
    hook.reset(torch.tensor([True]))
    assert hook.record(0)["carry_steps"] == 0
    assert carry_summary([r, {"carry_steps": 0}])["trials_with_carry"] == 1
