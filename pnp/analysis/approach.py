"""Where the gripper is while it approaches the unheld box, and just before the box tips.

    python recipes/analyze/approach.py checkpoint=results/run18_single_pnp_checkpoint.pt \
        out=runs/approach.json trials=100 seed=777 env.num_worlds=100

After every high-level step, for each robot whose box nobody holds: the EE's horizontal
distance to its handle (``xy``), its height above the handle's axis (``dz``, the "gripper
ready" condition wants -3..25 cm), its speed over the step and the gripper-handle
alignment. Reports the 10/50/90th percentiles over the steps with ``xy`` under ``near_m``
(the approach) and over the ``window`` steps up to the first step the box's tilt passed
``tilt_deg`` (the onset). The hand-run chain's policy holds the EE ~5 cm above the handle
near it; the pipeline's ~1 cm, with the fingers at the box's height (docs/history/pipeline_single/run_10.md).
"""
from __future__ import annotations

import math

import numpy as np
import torch
from omegaconf import OmegaConf

import pnp.task as T
from pnp.task import HL_DT
from pnp.training.rollout import GRABBED, box_up_z

from pnp.analysis.analysis_cli import OnsetWindow, hooked_trials, save, settings

DEFAULTS = {"checkpoint": None, "out": "runs/approach.json", "trials": 100, "seed": 777, "near_m": 0.15,
            "tilt_deg": 30.0, "window": 6, "env": {"num_worlds": 100}}
COLUMNS = ("xy", "dz", "speed", "align")


class Approach:
    """A :class:`pnp.training.rollout.TrialHook` sampling the EE-handle geometry of unheld boxes."""

    def __init__(self, n_worlds: int, near_m: float, tilt_deg: float, window: int, dt: float):
        self.near_m, self.cos, self.dt = near_m, math.cos(math.radians(tilt_deg)), dt
        self.onsets = OnsetWindow(n_worlds, window)  # samples: [R, 4] rows per step
        self.near: list[np.ndarray] = []
        self.last_ee: torch.Tensor | None = None  # [W, R, 3]; NaN after a reset: no speed on a first step

    def after_step(self, env, nxt) -> None:
        s = env.base_env.physical_state()
        g = T.geometry(s)
        speed = torch.full(s.ee_pos.shape[:2], math.nan) if self.last_ee is None else \
            (s.ee_pos - self.last_ee).norm(dim=-1) / self.dt
        self.last_ee = s.ee_pos.clone()
        rows = torch.stack([torch.hypot(g.ee_handle[..., 0], g.ee_handle[..., 1]), -g.ee_handle[..., 2], speed,
                            g.align], -1)  # [W, R, 4]
        unheld = ~nxt["agents"]["stage_conditions"][..., GRABBED].any(-1)
        near = unheld[:, None] & (rows[..., 0] < self.near_m)
        self.near.append(rows[near].numpy())
        up_z = box_up_z(nxt["agents"]["object"][:, 0])
        for w in torch.nonzero(unheld).flatten().tolist():
            self.onsets.push(w, rows[w].tolist(), float(up_z[w]) < self.cos)

    def record(self, world: int) -> dict:
        onset = self.onsets.onset[world]
        return {"onset": None if onset is None else [row for step in onset for row in step]}

    def reset(self, done: torch.Tensor) -> None:
        self.onsets.reset(done)
        if self.last_ee is not None:
            self.last_ee[done] = math.nan


def percentiles(rows: np.ndarray) -> dict:
    """10/50/90th percentiles of each column, NaN speeds (first steps) left out."""
    out = {}
    for i, name in enumerate(COLUMNS):
        col = rows[:, i][~np.isnan(rows[:, i])] if len(rows) else rows
        out[name] = [round(float(v), 4) for v in np.percentile(col, [10, 50, 90])] if len(col) else None
    return out


def approach(checkpoint: str, trials: int, seed: int, near_m: float, tilt_deg: float, window: int, **env) -> dict:
    records, hook, header = hooked_trials(
        checkpoint, trials, seed, lambda base: Approach(base.num_worlds, near_m, tilt_deg, window, dt=HL_DT), env)
    onsets = [r["onset"] for r in records if r["onset"]]
    near = np.concatenate(hook.near) if hook.near else np.zeros((0, len(COLUMNS)))
    return {**header, "near_m": near_m, "tilt_deg": tilt_deg, "window": window, "near_steps": len(near),
            "near": percentiles(near), "onsets": len(onsets),
            "before_onset": percentiles(np.array([row for o in onsets for row in o]).reshape(-1, len(COLUMNS)))}


def main(argv: list[str]) -> dict:
    cfg = settings(argv, DEFAULTS, __doc__)
    out = approach(cfg.checkpoint, int(cfg.trials), int(cfg.seed), float(cfg.near_m), float(cfg.tilt_deg),
                   int(cfg.window), **OmegaConf.to_container(cfg.env))
    save(out, cfg.out)
    print({k: out[k] for k in ("success_rate", "near", "onsets", "before_onset")})
    return out
