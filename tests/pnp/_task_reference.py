"""FROZEN reference copy of the ``pnp.task`` per-step functions, used only by
``tests/pnp/test_task_equivalence.py``: the straightforward (matmul/gather) implementation
the optimised ``pnp.task`` must reproduce. Do not edit or import it from library code.

Constants and the ``PnPState`` / ``Geometry`` dataclasses come from ``pnp.task`` so both
implementations see the same inputs and return the same types.
"""
from __future__ import annotations

import torch

from pnp.sim.box import HANDLE_HEIGHT, HANDLE_INSET, HANDLE_LEN
from pnp.sim.robot import ARM_DEFAULT, ARM_RANGES, FINGER_STROKE
from pnp.sim.scene import GOAL_RADIUS
from pnp.task import (
    ACTION_HIGH, ACTION_LOW, FALL_HEIGHT, FOOTPRINT_HALF, GRASP_DIST, LIFT_HEIGHT, MAX_OBJ_HEIGHT, OBS_BLOCKS, ON_FLOOR, READY_ALIGN,
    READY_XY, READY_Z, Geometry, PnPState,
)
from pnp.task.rewards import APPROACH_RADIUS, STANCE_M
from pnp.task.terms import CONDITIONS, REWARD_TABLE, REWARD_TERMS, STAGE_GATES, STAGE_PROGRESS_TERM


def yaw_rotation(yaw: torch.Tensor) -> torch.Tensor:
    c, s = torch.cos(yaw), torch.sin(yaw)
    z, o = torch.zeros_like(yaw), torch.ones_like(yaw)
    return torch.stack([torch.stack([c, -s, z], -1), torch.stack([s, c, z], -1), torch.stack([z, z, o], -1)], -2)


def to_base(s: PnPState, p: torch.Tensor) -> torch.Tensor:
    """World points ``p`` [N, R, ..., 3] into each robot's base frame."""
    origin = torch.cat([s.base[..., :2], s.base_z.unsqueeze(-1)], -1)
    rot = yaw_rotation(s.base[..., 2])
    extra = p.dim() - origin.dim()
    for _ in range(extra):
        origin, rot = origin.unsqueeze(-2), rot.unsqueeze(-3)
    return ((p - origin).unsqueeze(-2) @ rot).squeeze(-2)  # R^T (p - o)


def handles(s: PnPState) -> torch.Tensor:
    """Handle bar centres [N, 2, 3] in the world frame."""
    a, c = s.box_size[:, 0], s.box_size[:, 2]
    x = a / 2 - HANDLE_INSET
    z = c / 2 + HANDLE_HEIGHT
    local = torch.stack([torch.stack([x, torch.zeros_like(x), z], -1), torch.stack([-x, torch.zeros_like(x), z], -1)], 1)
    return s.box_pos.unsqueeze(1) + (s.box_rot.unsqueeze(1) @ local.unsqueeze(-1)).squeeze(-1)


def geometry(s: PnPState) -> Geometry:
    h = handles(s)  # [N, 2, 3]
    d = h.unsqueeze(1) - s.ee_pos.unsqueeze(2)  # [N, R, 2, 3]
    dist = d.norm(dim=-1)  # [N, R, 2]
    k = dist.argmin(-1)  # [N, R]
    if s.ee_pos.shape[1] == 2:  # two robots on one handle: the farther takes the other
        own = dist.gather(2, k.unsqueeze(-1)).squeeze(-1)
        same = k[:, 0] == k[:, 1]
        k = k.clone()
        k[same & (own[:, 0] > own[:, 1]), 0] ^= 1
        k[same & (own[:, 1] >= own[:, 0]), 1] ^= 1
    idx = k[..., None, None].expand(-1, -1, 1, 3)
    handle = torch.gather(h.unsqueeze(1).expand(-1, s.ee_pos.shape[1], -1, -1), 2, idx).squeeze(2)
    ee_handle = torch.gather(d, 2, idx).squeeze(2)
    bar_axis = s.box_rot[:, :, 1].unsqueeze(1)  # box y axis, [N, 1, 3]
    # Aligned when the gripper's closing axis (its y) is perpendicular to the bar.
    closing = s.ee_rot[..., :, 1]
    align = 1.0 - (closing * bar_axis).sum(-1).abs()
    half_len = torch.clamp(0.6 * s.box_size[:, 1], max=HANDLE_LEN).unsqueeze(1) / 2
    along = (ee_handle * bar_axis).sum(-1)
    perp = ee_handle - along.unsqueeze(-1) * bar_axis
    excess = torch.clamp(along.abs() - half_len, min=0.0)
    bar_dist = torch.sqrt((perp**2).sum(-1) + excess**2)
    closed = s.grasp_cmd > 0.5
    grasped = closed & s.touch.all(-1) & (bar_dist < GRASP_DIST)
    bottom = s.box_pos[:, 2] - _half_height(s)
    gd = (s.box_pos[:, :2] - s.goal).norm(dim=-1)
    return Geometry(
        handle=handle, own=k == 1, ee_handle=ee_handle, align=align, bar_dist=bar_dist, grasped=grasped,
        box_lift=bottom, box_goal_dist=gd, box_in_goal=gd < GOAL_RADIUS, box_on_floor=bottom < ON_FLOOR,
        fell=s.base_z < FALL_HEIGHT,
    )


def _half_height(s: PnPState) -> torch.Tensor:
    # Half extent of the (possibly tilted) box along world z.
    return 0.5 * (s.box_rot.abs() @ s.box_size.unsqueeze(-1)).squeeze(-1)[:, 2]


def stage_conditions(s: PnPState, g: Geometry) -> torch.Tensor:
    """Bool [N, R, len(CONDITIONS)]; column i is the condition of edge S_i -> S_{i+1}."""
    R = s.ee_pos.shape[1]
    dz = -g.ee_handle[..., 2]  # EE above the handle axis
    ready = (g.ee_handle[..., :2].norm(dim=-1) < READY_XY) & (dz > READY_Z[0]) & (dz < READY_Z[1]) & (g.align > READY_ALIGN)
    if R == 2:
        ready = ready | g.grasped  # two robots: a held handle counts as ready (ours, see pnp.task.conditions)
    box = lambda x: x.unsqueeze(1).expand(-1, R)  # noqa: E731  shared box conditions
    lifted = g.grasped & box(g.box_lift > LIFT_HEIGHT)
    on_goal = lifted & box(g.box_in_goal)
    placed = g.grasped & box(g.box_on_floor & g.box_in_goal)
    released = ~g.grasped & (s.grasp_cmd < 0.5) & box(g.box_on_floor & g.box_in_goal)
    out = torch.stack([ready, g.grasped, lifted, on_goal, placed, released], -1)
    assert out.shape[-1] == len(CONDITIONS)
    return out


def reward_terms(s: PnPState, g: Geometry, action: torch.Tensor, last_action: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
    """Float [N, R, len(REWARD_TERMS)] in the order of ``pnp.task.terms.REWARD_TERMS``."""
    R = s.ee_pos.shape[1]
    box = lambda x: x.unsqueeze(1).expand(-1, R)  # noqa: E731
    p = s.grasp_cmd
    grabbed = g.grasped.float()
    height = torch.clamp(g.box_lift, 0.0, MAX_OBJ_HEIGHT)
    to_goal = torch.cat([s.goal - s.box_pos[:, :2], torch.zeros_like(s.goal[:, :1])], -1)
    to_goal = to_goal / to_goal.norm(dim=-1, keepdim=True).clamp(min=1e-6)
    v_goal = (s.box_vel[:, :3] * to_goal).sum(-1)
    lo, hi = _action_bounds(action)
    scale = (hi - lo) / 2
    lim = torch.tensor(ARM_RANGES, dtype=s.arm_q.dtype)
    mid, half = (lim[:, 0] + lim[:, 1]) / 2, (lim[:, 1] - lim[:, 0]) / 2
    collision = _collisions(s)
    terms = {
        "gripper_ready_pose": torch.exp(-3 * g.ee_handle[..., :2].norm(dim=-1)) * g.align,
        "gripper_grasp_pose": torch.exp(-10 * g.ee_handle[..., 2].abs()) * g.align,
        "object_grabbed": grabbed,
        "grab_action": torch.where(g.grasped, p, 1 - p),
        "object_height": box(height),
        "object_to_goal_vel": box(torch.clamp(1 - torch.exp(-2 * v_goal), -1.0, 1.0)),
        "object_to_goal_dist": box(torch.exp(-2 * g.box_goal_dist / s.init_goal_dist.clamp(min=1e-3))),
        "object_drop": box(MAX_OBJ_HEIGHT - height),
        "grab_action_in_range": torch.clamp(0.5 - p, min=0.0),
        "object_released_in_goal": cond[..., 5].float(),
        "stage_progress": torch.zeros_like(p),
        "arm_default_pose": torch.exp(-2 * (s.arm_q - torch.tensor(ARM_DEFAULT, dtype=p.dtype)).norm(dim=-1)),
        "action_rate": (((action - last_action) / scale) ** 2).sum(-1),
        "collision": collision,
        "joint_limits": torch.clamp((s.arm_q - mid).abs() - 0.95 * half, min=0.0).sum(-1),
        "fall": g.fell.float(),
        "gripper_toggle": ((action[..., 7] > 0.5).ne(last_action[..., 7] > 0.5) & ~g.grasped).float(),
        "object_tilt": (1 - s.box_rot[:, None, 2, 2]).expand(-1, R) * (~g.grasped.any(1, keepdim=True)).float(),
        "base_approach": _base_approach(s, g),
        "base_stance": _base_stance(s, g),
    }
    return torch.stack([terms[n] for n in REWARD_TERMS], -1)


def _base_approach(s: PnPState, g: Geometry) -> torch.Tensor:
    to_handle = g.ee_handle[..., :2]
    dist = to_handle.norm(dim=-1)
    speed = (s.base_vel[..., :2] * to_handle).sum(-1) / dist.clamp(min=1e-6)
    pays = (dist > APPROACH_RADIUS) & ~g.grasped.any(1, keepdim=True)
    return speed.clamp(-1.0, 1.0) * pays.float()


def _base_stance(s: PnPState, g: Geometry) -> torch.Tensor:
    near, far = STANCE_M
    dist = (g.handle[..., :2] - s.base[..., :2]).norm(dim=-1)
    share = torch.clamp((far - dist) / (far - near), 0.0, 1.0)
    return share * (~g.grasped.any(1, keepdim=True)).float()


def _action_bounds(action):
    lo = torch.tensor(ACTION_LOW, dtype=action.dtype, device=action.device)
    hi = torch.tensor(ACTION_HIGH, dtype=action.dtype, device=action.device)
    return lo, hi


def _collisions(s: PnPState) -> torch.Tensor:
    """Footprint rectangles (world frame, from corners) overlapping the box's or each other's."""
    R = s.base.shape[1]
    robot = [_corners(s.base[:, r, :2], s.base[:, r, 2], FOOTPRINT_HALF) for r in range(R)]
    box_yaw = torch.atan2(s.box_rot[:, 1, 0], s.box_rot[:, 0, 0])
    box = _corners(s.box_pos[:, :2], box_yaw, (s.box_size[:, 0] / 2, s.box_size[:, 1] / 2))
    hit = torch.stack([_sat(robot[r], box) for r in range(R)], 1)
    if R == 2:
        hit = hit | _sat(robot[0], robot[1]).unsqueeze(1)
    return hit.float()


def _corners(centre: torch.Tensor, yaw: torch.Tensor, half) -> torch.Tensor:
    """[N, 4, 2] corners of rectangles with half extents ``half`` (floats or [N])."""
    hx, hy = (torch.as_tensor(h, dtype=centre.dtype).expand(centre.shape[0]) for h in half)
    local = torch.stack([torch.stack([sx * hx, sy * hy], -1) for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1))], 1)
    return centre.unsqueeze(1) + local @ yaw_rotation(yaw)[:, :2, :2].transpose(-1, -2)


def _sat(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Overlap of convex polygons [N, 4, 2] by projecting both on every edge normal."""
    overlap = torch.ones(a.shape[0], dtype=torch.bool)
    for poly in (a, b):
        for k in range(2):
            edge = poly[:, k + 1] - poly[:, k]
            axis = torch.stack([-edge[:, 1], edge[:, 0]], -1)
            pa, pb = ((x @ axis.unsqueeze(-1)).squeeze(-1) for x in (a, b))  # [N, 4]
            overlap &= (pa.max(1).values >= pb.min(1).values) & (pb.max(1).values >= pa.min(1).values)
    return overlap


def observations(s: PnPState, g: Geometry, last_action: torch.Tensor) -> dict[str, torch.Tensor]:
    """Named observation blocks [N, R, k] (sizes in :data:`OBS_BLOCKS`)."""
    N, R = s.ee_pos.shape[:2]
    rot = yaw_rotation(s.base[..., 2])
    vel_b = (s.base_vel[..., :2].unsqueeze(-2) @ rot[..., :2, :2]).squeeze(-2)
    ee_b = to_base(s, s.ee_pos)
    ee_rot_b = rot.transpose(-1, -2) @ s.ee_rot
    ee_yaw = torch.atan2(-ee_rot_b[..., 0, 1], ee_rot_b[..., 1, 1])
    opening = s.finger_q.mean(-1, keepdim=True) / FINGER_STROKE
    ego = torch.cat([
        vel_b, s.base_vel[..., 2:], s.arm_q, s.arm_qd * 0.1, ee_b, torch.sin(ee_yaw)[..., None], torch.cos(ee_yaw)[..., None],
        opening, s.touch.float(), last_action,
    ], -1)
    goal3 = torch.cat([s.goal, torch.zeros_like(s.goal[:, :1])], -1).unsqueeze(1).expand(N, R, 3)
    goal_b = to_base(s, goal3)[..., :2]
    goal = torch.cat([goal_b, goal_b.norm(dim=-1, keepdim=True)], -1)
    h = handles(s).unsqueeze(1).expand(N, R, 2, 3)
    box_rot_b = rot.transpose(-1, -2) @ s.box_rot.unsqueeze(1)
    lin_b = (s.box_vel[:, None, None, :3] @ rot).squeeze(-2)
    ang_b = (s.box_vel[:, None, None, 3:] @ rot).squeeze(-2)
    h_b = to_base(s, h)
    obj = torch.cat([
        to_base(s, s.box_pos.unsqueeze(1).expand(N, R, 3)), box_rot_b[..., :, 0], box_rot_b[..., :, 1],
        lin_b, ang_b, h_b.flatten(-2), (h_b - ee_b.unsqueeze(-2)).flatten(-2), s.box_size.unsqueeze(1).expand(N, R, 3),
    ], -1)
    if R == 2:
        other = torch.tensor([1, 0])
        o_base = torch.cat([s.base[:, other, :2], s.base_z[:, other, None]], -1)
        rel = to_base(s, o_base)[..., :2]
        dyaw = s.base[:, other, 2] - s.base[..., 2]
        neigh = torch.cat([
            rel, torch.sin(dyaw)[..., None], torch.cos(dyaw)[..., None], to_base(s, s.ee_pos[:, other]),
            opening[:, other], s.touch[:, other].float(),
        ], -1)
    else:
        neigh = torch.zeros(N, R, OBS_BLOCKS["neighbour"], dtype=ego.dtype)
    return {"ego": ego, "goal": goal, "object": obj, "neighbour": neigh}


def default_reward(terms: torch.Tensor) -> torch.Tensor:
    """The env's own reward with no curriculum: every term at mu_j (stage-dependent ones off)."""
    w = [0.0 if (t.name in STAGE_GATES or t.name == STAGE_PROGRESS_TERM) else t.mu for t in REWARD_TABLE]
    return (terms * torch.tensor(w, dtype=terms.dtype)).sum(-1, keepdim=True)
