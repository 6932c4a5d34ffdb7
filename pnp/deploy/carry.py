"""How much two robots pull against each other while they carry the box together (the
paper's "under communication delays, robots resist each other instead of adapting").

Measured as the distance between the two grippers: the box is rigid and held at its two
handles, so a pair that moves as one keeps that distance; when one robot pulls the other
way the grasps give and the distance moves. The carry starts at the first step where both
robots hold the box with it lifted; the reference is the distance there.
"""
from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDictBase

from pnp.training.rollout import GRABBED, LIFTED


class CarryStrain:
    """``run_trials`` hook: per episode, the steps of the two-robot carry and the mean and
    largest change of the gripper-to-gripper distance (m) from its value when the carry began."""

    def __init__(self, worlds: int):
        self.start = torch.full((worlds,), float("nan"))
        self.steps = torch.zeros(worlds, dtype=torch.long)
        self.dev_sum = torch.zeros(worlds)
        self.dev_max = torch.zeros(worlds)
        self._done = torch.zeros(worlds, dtype=torch.bool)

    def after_step(self, env, nxt: TensorDictBase) -> None:
        cond = nxt["agents", "stage_conditions"]
        if cond.shape[-2] != 2:
            raise ValueError(f"CarryStrain measures a pair; this env has {cond.shape[-2]} robot(s)")
        ee = env.base_env.physical_state().ee_pos  # [W, 2, 3]; worlds done this step are already reset
        distance = (ee[:, 0] - ee[:, 1]).norm(dim=-1)
        done = nxt["done"].view(-1)
        carrying = cond[..., GRABBED].all(-1) & cond[..., LIFTED].any(-1) & ~done
        begin = carrying & self.start.isnan()
        self.start = torch.where(begin, distance, self.start)
        dev = (distance - self.start).abs()
        self.steps += carrying.long()
        self.dev_sum += torch.where(carrying, dev, torch.zeros_like(dev))
        self.dev_max = torch.where(carrying, torch.maximum(self.dev_max, dev), self.dev_max)

    def record(self, world: int) -> dict:
        n = int(self.steps[world])
        return {"carry_steps": n, "grip_distance_change_mean_m": float(self.dev_sum[world]) / n if n else None,
                "grip_distance_change_max_m": float(self.dev_max[world]) if n else None}

    def reset(self, done: torch.Tensor) -> None:
        self.start[done] = float("nan")
        self.steps[done], self.dev_sum[done], self.dev_max[done] = 0, 0.0, 0.0


def carry_summary(records: list[dict]) -> dict:
    """Over the trials that carried: how many, and the mean / p90 of their mean and largest change."""
    carried = [r for r in records if r.get("carry_steps")]
    if not carried:
        return {"trials_with_carry": 0}
    mean = np.array([r["grip_distance_change_mean_m"] for r in carried])
    peak = np.array([r["grip_distance_change_max_m"] for r in carried])
    return {"trials_with_carry": len(carried), "change_mean_m": float(mean.mean()),
            "change_max_mean_m": float(peak.mean()), "change_max_p90_m": float(np.percentile(peak, 90))}
