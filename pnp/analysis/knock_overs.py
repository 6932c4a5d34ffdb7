"""How often a checkpoint's deterministic policy knocks the box over, and whether it recovers.

    python recipes/analyze/knock_overs.py checkpoint=results/run18_single_pnp_checkpoint.pt \
        out=runs/knock_overs.json trials=200 seed=777 env.num_worlds=200

Per trial (``pnp.training.rollout.run_trials``): whether the box lay unheld with its up axis
beyond ``tilt_rad`` (default: the ``tipped_box`` failure's 60 deg) for ``lie_steps`` steps in a
row (tipped), and how often the gripper
command changed between consecutive steps while the robot was in S0 (toggles). Reports the
tipped trials and how many of them still succeeded, the toggles per S0 step, and the mean
steps of successes with and without a tip (docs/history/pipeline_single/failures.md: run 6's
policy tipped the box in 55 of 200 trials, the hand-run chain's in 32).
"""
from __future__ import annotations

import math

import numpy as np
import torch
from omegaconf import OmegaConf

from pnp.task import OBS_FIELDS
from pnp.training.keys import STAGE
from pnp.training.rollout import GRABBED, TIPPED_TILT, box_up_z

from pnp.analysis.analysis_cli import hooked_trials, save, settings

_GRASP_CMD = OBS_FIELDS["ego"]["last_action"].start + 7  # the action just taken: its grasp entry
DEFAULTS = {"checkpoint": None, "out": "runs/knock_overs.json", "trials": 200, "seed": 777, "tilt_rad": TIPPED_TILT,
            "lie_steps": 5, "env": {"num_worlds": 100}}


class KnockOvers:
    """A :class:`pnp.training.rollout.TrialHook` counting tips and S0 gripper toggles per world."""

    def __init__(self, n_worlds: int, tilt_rad: float, lie_steps: int):
        self.cos, self.lie_steps = math.cos(tilt_rad), int(lie_steps)
        self.lying = torch.zeros(n_worlds, dtype=torch.long)
        self.tipped = torch.zeros(n_worlds, dtype=torch.bool)
        self.toggles = torch.zeros(n_worlds, dtype=torch.long)
        self.s0_steps = torch.zeros(n_worlds, dtype=torch.long)
        self.last_cmd = torch.full((n_worlds,), -1.0)  # none yet this episode

    def after_step(self, env, nxt) -> None:
        agents = nxt["agents"]
        held = agents["stage_conditions"][..., GRABBED].any(-1)
        down = ~held & (box_up_z(agents["object"][:, 0]) < self.cos)
        self.lying = torch.where(down, self.lying + 1, torch.zeros_like(self.lying))
        self.tipped |= self.lying >= self.lie_steps
        cmd = (agents["ego"][..., _GRASP_CMD] > 0.5).any(-1).float()
        s0 = nxt[STAGE].reshape(len(cmd), -1).max(-1).values == 0
        self.toggles += (s0 & (self.last_cmd >= 0) & (cmd != self.last_cmd)).long()
        self.s0_steps += s0.long()
        self.last_cmd = cmd

    def record(self, world: int) -> dict:
        return {"tipped": bool(self.tipped[world]), "s0_toggles": int(self.toggles[world]),
                "s0_steps": int(self.s0_steps[world])}

    def reset(self, done: torch.Tensor) -> None:
        for t in (self.lying, self.toggles, self.s0_steps):
            t[done] = 0
        self.tipped[done] = False
        self.last_cmd[done] = -1.0


def knock_overs(checkpoint: str, trials: int, seed: int, tilt_rad: float, lie_steps: int, **env) -> dict:
    records, _, header = hooked_trials(checkpoint, trials, seed,
                                       lambda base: KnockOvers(base.num_worlds, tilt_rad, lie_steps), env)
    tipped = [r for r in records if r["tipped"]]
    steps = lambda rs: float(np.mean([r["steps"] for r in rs])) if rs else None  # noqa: E731
    s0 = sum(r["s0_steps"] for r in records)
    return {**header, "tilt_rad": tilt_rad, "lie_steps": lie_steps, "tipped_trials": len(tipped),
            "tipped_and_succeeded": sum(r["success"] for r in tipped),
            "s0_toggles_per_step": sum(r["s0_toggles"] for r in records) / s0 if s0 else None,
            "success_steps_mean": {"tipped": steps([r for r in tipped if r["success"]]),
                                   "not_tipped": steps([r for r in records if r["success"] and not r["tipped"]])}}


def main(argv: list[str]) -> dict:
    cfg = settings(argv, DEFAULTS, __doc__)
    out = knock_overs(cfg.checkpoint, int(cfg.trials), int(cfg.seed), float(cfg.tilt_rad), int(cfg.lie_steps),
                      **OmegaConf.to_container(cfg.env))
    save(out, cfg.out)
    print({k: out[k] for k in ("success_rate", "tipped_trials", "tipped_and_succeeded", "s0_toggles_per_step",
                               "failure_causes")})
    return out
