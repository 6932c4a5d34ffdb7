"""A scripted policy for the EE tracking task: walk until the current point is ``STAND_X``
ahead, facing it, and put the EE on it. It proves the four stages are reachable in order
and gives a reference completion time.
"""
from __future__ import annotations

import torch
from tensordict import TensorDictBase

from pnp.task.ee_tracking import EE_OBS_FIELDS, N_POINTS, TOUCH_TOL
from pnp.task import ACTION_HIGH, ACTION_LOW

STAND_X = 0.9  # m: a base-frame x where every sampled height is reachable (see POINT_HEIGHT)


class ScriptedEETracking:
    """Counts touched points from the observed distances (the env's forward-only rule);
    call :meth:`reset` with the mask of worlds that restarted."""

    def __init__(self, num_worlds: int):
        self.touched = torch.zeros(num_worlds, dtype=torch.long)
        self.lo, self.hi = torch.tensor(ACTION_LOW), torch.tensor(ACTION_HIGH)

    def reset(self, mask: torch.Tensor) -> None:
        self.touched[mask.reshape(-1)] = 0

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        obs = td.get(("agents", "points"))[:, 0]
        pts = obs[:, EE_OBS_FIELDS["points"]["points_pos"]].unflatten(-1, (N_POINTS, 3))
        dist = obs[:, EE_OBS_FIELDS["points"]["points_dist"]]
        k = self.touched.clamp(max=N_POINTS - 1)
        self.touched += ((dist.gather(-1, k[:, None]).squeeze(-1) < TOUCH_TOL) & (self.touched < N_POINTS)).long()
        k = self.touched.clamp(max=N_POINTS - 1)
        p = pts.gather(1, k[:, None, None].expand(-1, 1, 3)).squeeze(1)  # current point, base frame
        heading = torch.atan2(p[:, 1], p[:, 0])
        a = torch.zeros(len(p), 8)
        a[:, 0] = 1.5 * (p[:, 0] - STAND_X) * torch.cos(heading).clamp(min=0.0)  # turn first when it is behind
        a[:, 1] = 1.5 * p[:, 1]
        a[:, 2] = 2.0 * heading
        # Hold the EE ahead at the point's height until the point is there: EE commands
        # near the shoulder can trap the MuJoCo executor's DLS IK at its joint limits.
        near = ((p[:, 0] - STAND_X).abs() < 0.3) & (p[:, 1].abs() < 0.3)
        ahead = torch.stack([torch.full_like(p[:, 0], STAND_X), torch.zeros_like(p[:, 1]), p[:, 2]], -1)
        a[:, 3:6] = torch.where(near[:, None], p, ahead)
        td.set(("agents", "action"), torch.max(torch.min(a, self.hi), self.lo).unsqueeze(1))
        return td
