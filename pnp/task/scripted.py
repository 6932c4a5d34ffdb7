"""A scripted pick-and-place policy acting on the env's observation blocks, for 1 or 2 robots.

Approach a handle from outside the box, descend, grasp, lift, carry the box to the goal,
lower it and release. One robot takes the nearer handle. Two robots split the handles
(the assignment with the shorter summed distance, fixed at the episode start) and move
in lockstep: neither lifts, lowers nor releases before both are ready (``SYNCED``), and
both carry at the same world velocity. It proves the stage conditions are reachable on
every backend and gives the rendering and benchmark recipes meaningful motion.
"""
from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase

from pnp.task import ACTION_HIGH, ACTION_LOW, OBS_FIELDS

APPROACH, DESCEND, GRASP, LIFT, CARRY, LOWER, RELEASE = range(7)
SYNCED = (GRASP, LIFT, CARRY, LOWER)  # with two robots, leaving these waits for both
REACH_X = 0.75  # m, handle distance in front of the base when grasping (default EE x)
HOVER = 0.15  # m above the handle before descending
LIFT_BY = 0.4  # m: a box hanging from one handle tilts, its low corner must clear
CARRY_SPEED_2 = 0.45  # m/s, two robots: under the 0.5 m/s lateral clip in any heading
LIFT_BY_2, RAMP_2 = 0.15, 0.015  # m and m per step, two robots


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
        self.handle = torch.zeros(shape, dtype=torch.long)  # index of the handle each robot takes
        self.assigned = torch.zeros(num_worlds, dtype=torch.bool)
        self._synced = torch.tensor(SYNCED)
        self.lo, self.hi = torch.tensor(ACTION_LOW), torch.tensor(ACTION_HIGH)

    def reset(self, mask: torch.Tensor) -> None:
        mask = mask.reshape(-1)
        self.phase[mask] = APPROACH
        self.timer[mask] = 0
        self.assigned[mask] = False

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        handles = _field(td, "object", "handles").unflatten(-1, (2, 3))
        box = _field(td, "object", "box_pos")
        bar = _field(td, "object", "box_y_axis")
        ee = _field(td, "ego", "ee_pos")
        goal = _field(td, "goal", "goal_xy")
        self._assign(handles[..., :2].norm(dim=-1))
        k = self.handle.unsqueeze(-1)
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
        two = ph.shape[1] == 2
        # Two robots hold a level box: a small lift, ramped so both arms rise together
        # (heights apart by more than the grasp tolerance pull a handle out of a gripper).
        lift_by = LIFT_BY_2 if two else LIFT_BY
        ramp = torch.clamp(RAMP_2 * self.timer, max=lift_by) if two else torch.full_like(self.z_grasp, lift_by)
        for p in (LIFT, CARRY):
            m = ph == p
            a[m, 0:3] = 0.0
            a[m, 3:5] = self.ee_grasp[m]
            a[m, 5] = (self.z_grasp + (ramp if p == LIFT else lift_by))[m]
        self._advance(ph == LIFT, (box[..., 2] - self.box_z0 > 0.08) & (ramp >= lift_by))
        c = ph == CARRY
        to_goal = goal - box[..., :2]
        v = 1.2 * to_goal
        if v.shape[1] == 2:  # one world speed for both, below every clip: the bases keep their spacing
            v = v * (CARRY_SPEED_2 / v.norm(dim=-1, keepdim=True).clamp(min=CARRY_SPEED_2))
        a[c, 0:2] = v[c]
        self._advance(c, to_goal.norm(dim=-1) < 0.12)
        lw = ph == LOWER
        a[lw, 0:3] = 0.0
        a[lw, 3:5] = self.ee_grasp[lw]
        down = torch.clamp(lift_by - RAMP_2 * self.timer, min=0.005) if two else torch.full_like(self.z_grasp, 0.005)
        a[lw, 5] = (self.z_grasp + down)[lw]
        self._advance(lw, self.timer > (10 + lift_by / RAMP_2 if two else 10))
        r = ph == RELEASE
        a[r, 0:3] = 0.0
        a[r, 3:5] = self.ee_grasp[r]
        a[r, 5] = torch.where(self.timer[r] > 4, self.z_grasp[r] + HOVER, self.z_grasp[r])
        td.set(("agents", "action"), torch.max(torch.min(a, self.hi), self.lo))
        return td

    def _assign(self, dist: torch.Tensor) -> None:
        """Handles for worlds not yet assigned; ``dist`` [N, R, 2]: base to each handle."""
        new = ~self.assigned
        if not new.any():
            return
        if dist.shape[1] == 1:
            pick = dist.argmin(-1)
        else:  # robot 0 takes handle 0 (robot 1 handle 1) or the swap, whichever is shorter
            swap = dist[:, 0, 1] + dist[:, 1, 0] < dist[:, 0, 0] + dist[:, 1, 1]
            pick = torch.stack([swap.long(), 1 - swap.long()], -1)
        self.handle = torch.where(new.unsqueeze(-1), pick, self.handle)
        self.assigned |= new

    def _advance(self, where: torch.Tensor, cond: torch.Tensor) -> None:
        """Move the robots in ``where`` (all in one phase) on where ``cond`` holds."""
        go = where & cond
        if go.shape[1] == 2:
            # Lockstep phases: a robot leaves only together with its partner.
            synced = where & torch.isin(self.phase, self._synced)
            go = torch.where(synced, go.all(-1, keepdim=True).expand_as(go), go)
        self.phase = torch.where(go, self.phase + 1, self.phase)
        self.timer = torch.where(go, torch.zeros_like(self.timer), self.timer)
