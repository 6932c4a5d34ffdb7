"""A scripted single-robot pick-and-place policy acting on the env's observation blocks.

Approach the nearer handle from outside the box, descend, grasp, lift, carry the box to
the goal, lower it and release. It proves the stage conditions are reachable on every
backend and gives the rendering and benchmark recipes meaningful motion.
"""
from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase

from pnp.task import ACTION_HIGH, ACTION_LOW, OBS_FIELDS

APPROACH, DESCEND, GRASP, LIFT, CARRY, LOWER, RELEASE = range(7)
REACH_X = 0.75  # m, handle distance in front of the base when grasping (default EE x)
HOVER = 0.15  # m above the handle before descending
LIFT_BY = 0.4  # m: a box hanging from one handle tilts, its low corner must clear


def _field(td, block, name):
    return td.get(("agents", block))[..., OBS_FIELDS[block][name]]


class ScriptedPnP:
    """Batched state machine; call :meth:`reset` with the mask of worlds that restarted."""

    def __init__(self, num_worlds: int, num_robots: int = 1):
        shape = (num_worlds, num_robots)
        self.phase = torch.zeros(shape, dtype=torch.long)
        self.timer = torch.zeros(shape, dtype=torch.long)
        self.z_grasp = torch.zeros(shape)
        self.box_z0 = torch.zeros(shape)
        self.ee_grasp = torch.zeros(*shape, 2)
        self.lo, self.hi = torch.tensor(ACTION_LOW), torch.tensor(ACTION_HIGH)

    def reset(self, mask: torch.Tensor) -> None:
        mask = mask.reshape(-1)
        self.phase[mask] = APPROACH
        self.timer[mask] = 0

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        handles = _field(td, "object", "handles").unflatten(-1, (2, 3))
        box = _field(td, "object", "box_pos")
        bar = _field(td, "object", "box_y_axis")
        ee = _field(td, "ego", "ee_pos")
        goal = _field(td, "goal", "goal_xy")
        k = handles[..., :2].norm(dim=-1).argmin(-1, keepdim=True)
        h = torch.gather(handles, -2, k[..., None].expand(*k.shape, 3)).squeeze(-2)
        u = box[..., :2] - h[..., :2]
        u = u / u.norm(dim=-1, keepdim=True).clamp(min=1e-6)  # from handle into the box
        stand = h[..., :2] - REACH_X * u  # where the base should be (base frame)
        heading = torch.atan2(u[..., 1], u[..., 0])
        yaw = torch.atan2(bar[..., 1], bar[..., 0])
        yaw = torch.remainder(yaw + math.pi / 2, math.pi) - math.pi / 2  # gripper is symmetric
        ph, self.timer = self.phase, self.timer + 1
        a = torch.zeros(*ph.shape, 8)
        # Base: go to the stand point, staying clear of the box until lined up behind it.
        far = stand.norm(dim=-1, keepdim=True) > 0.4
        staging = h[..., :2] - (REACH_X + 0.6) * u
        tgt = torch.where(far & (staging.norm(dim=-1, keepdim=True) > 0.3), staging, stand)
        v = 1.5 * tgt
        a[..., 0:2] = v
        a[..., 2] = 2.0 * heading
        a[..., 3:6] = h + torch.tensor([0.0, 0.0, HOVER])
        a[..., 6] = yaw
        hover_err = (ee - (h + torch.tensor([0.0, 0.0, HOVER]))).norm(dim=-1)
        ready = (stand.norm(dim=-1) < 0.04) & (heading.abs() < 0.08) & (hover_err < 0.03)
        self._advance(ph == APPROACH, ready)
        d = ph == DESCEND
        a[d, 3:6] = h[d]
        self._advance(d, (ee - h).norm(dim=-1) < 0.012)
        self.z_grasp = torch.where(d, h[..., 2], self.z_grasp)
        self.box_z0 = torch.where(d, box[..., 2], self.box_z0)
        held = ph >= GRASP
        a[..., 7] = torch.where(held & (ph < RELEASE), 1.0, 0.0)
        g = ph == GRASP
        self.ee_grasp = torch.where(g.unsqueeze(-1), ee[..., :2], self.ee_grasp)
        a[g, 0:3] = 0.0
        a[g, 3:6] = h[g]
        self._advance(g, self.timer >= 4)
        for p in (LIFT, CARRY):
            m = ph == p
            a[m, 0:3] = 0.0
            a[m, 3:5] = self.ee_grasp[m]
            a[m, 5] = (self.z_grasp + LIFT_BY)[m]
        self._advance(ph == LIFT, box[..., 2] - self.box_z0 > 0.08)
        c = ph == CARRY
        to_goal = goal - box[..., :2]
        a[c, 0:2] = (1.2 * to_goal)[c]
        self._advance(c, to_goal.norm(dim=-1) < 0.12)
        lw = ph == LOWER
        a[lw, 0:3] = 0.0
        a[lw, 3:5] = self.ee_grasp[lw]
        a[lw, 5] = self.z_grasp[lw] + 0.005
        self._advance(lw, self.timer > 10)
        r = ph == RELEASE
        a[r, 0:3] = 0.0
        a[r, 3:5] = self.ee_grasp[r]
        a[r, 5] = torch.where(self.timer[r] > 4, self.z_grasp[r] + HOVER, self.z_grasp[r])
        td.set(("agents", "action"), torch.max(torch.min(a, self.hi), self.lo))
        return td

    def _advance(self, where: torch.Tensor, cond: torch.Tensor) -> None:
        go = where & cond
        self.phase = torch.where(go, self.phase + 1, self.phase)
        self.timer = torch.where(go, torch.zeros_like(self.timer), self.timer)
