"""The reward terms of pick-and-place (``pnp.task.terms.REWARD_TABLE``: Table II, then R_fixed),
per robot, from the task geometry, and the env's reward without a curriculum."""
from __future__ import annotations

import torch

from pnp.sim.robot import ARM_DEFAULT, ARM_RANGES
from pnp.task.geometry import FOOTPRINT_HALF, BaseFrame, Geometry, rects_overlap
from pnp.task.state import ACTION_HIGH, ACTION_LOW, PnPState
from pnp.task.terms import CONDITIONS, REWARD_TABLE, REWARD_TERMS, STAGE_GATES, STAGE_PROGRESS_TERM

MAX_OBJ_HEIGHT = 0.3  # m, "max height" of Table II's object height / drop terms
APPROACH_RADIUS = 0.5  # m, EE to handle (horizontal); base_approach pays only beyond it
# m, base to handle (horizontal) where base_stance pays in full / nothing: the default arm pose's
# EE is 0.75 m ahead of the base; ~1.05 m is the arm's full reach at a handle's height.
STANCE_M = (0.75, 1.05)
# What gripper_grasp_pose measures (env.grasp_pose): the EE's height above its handle's axis
# (our reading of Table II), or its distance to the handle bar (ours). The height alone pays
# nothing for the horizontal centimetres a grasp needs, which the ready pose's exp(-3 x) hardly
# tells apart (0.77 at 8.6 cm, 0.90 at 3.5 cm).
GRASP_POSES = ("height", "bar")

# Constant tensors, built once (CPU, float32).
_F32 = torch.float32
_INV_SCALE = 2.0 / (torch.tensor(ACTION_HIGH, dtype=_F32) - torch.tensor(ACTION_LOW, dtype=_F32))  # 1 / half range
_LIM = torch.tensor(ARM_RANGES, dtype=_F32)
_MID, _HALF95 = (_LIM[:, 0] + _LIM[:, 1]) / 2, 0.95 * (_LIM[:, 1] - _LIM[:, 0]) / 2
_ARM_DEFAULT = torch.tensor(ARM_DEFAULT, dtype=_F32)
# default_reward's weights as a column: one matmul instead of a product and a sum over terms.
_DEFAULT_MU = torch.tensor(
    [[0.0 if (t.name in STAGE_GATES or t.name == STAGE_PROGRESS_TERM) else t.mu] for t in REWARD_TABLE], dtype=_F32,
)
_RELEASED = CONDITIONS.index("object_released")


def reward_terms(s: PnPState, g: Geometry, action: torch.Tensor, last_action: torch.Tensor, cond: torch.Tensor,
                 frame: BaseFrame | None = None, grasp_pose: str = "height") -> torch.Tensor:
    """Float [N, R, len(REWARD_TERMS)] in the order of ``pnp.task.terms.REWARD_TERMS``;
    ``grasp_pose`` one of :data:`GRASP_POSES`."""
    R = s.ee_pos.shape[1]
    box = lambda x: x.unsqueeze(1).expand(-1, R)  # noqa: E731
    p = action[..., 7]  # the policy's grasp probability (Table II's grab action terms)
    height = torch.clamp(g.box_lift, 0.0, MAX_OBJ_HEIGHT)
    tx, ty = s.goal[:, 0] - s.box_pos[:, 0], s.goal[:, 1] - s.box_pos[:, 1]
    v_goal = (s.box_vel[:, 0] * tx + s.box_vel[:, 1] * ty) / torch.hypot(tx, ty).clamp(min=1e-6)
    dq = s.arm_q - _ARM_DEFAULT
    reach = torch.hypot(g.ee_handle[..., 0], g.ee_handle[..., 1])
    towards = (s.base_vel[..., 0] * g.ee_handle[..., 0] + s.base_vel[..., 1] * g.ee_handle[..., 1]) / reach.clamp(min=1e-6)
    unheld = ~g.grasped.any(1, keepdim=True)
    far = (reach > APPROACH_RADIUS) & unheld
    stance = torch.hypot(g.handle[..., 0] - s.base[..., 0], g.handle[..., 1] - s.base[..., 1])
    stance = ((STANCE_M[1] - stance) / (STANCE_M[1] - STANCE_M[0])).clamp(0.0, 1.0)
    terms = {
        "gripper_ready_pose": torch.exp(-3 * reach) * g.align,
        "gripper_grasp_pose": torch.exp(-10 * _grasp_pose_dist(g, grasp_pose)) * g.align,
        "object_grabbed": g.grasped.float(),
        "grab_action": torch.where(g.grasped, p, 1 - p),
        "object_height": box(height),
        "object_to_goal_vel": box(torch.clamp(1 - torch.exp(-2 * v_goal), -1.0, 1.0)),
        "object_to_goal_dist": box(torch.exp(-2 * g.box_goal_dist / s.init_goal_dist.clamp(min=1e-3))),
        "object_drop": box(MAX_OBJ_HEIGHT - height),
        "grab_action_in_range": torch.clamp(0.5 - p, min=0.0),
        "object_released_in_goal": cond[..., _RELEASED].float(),
        "stage_progress": torch.zeros_like(p),
        "arm_default_pose": torch.exp(-2 * torch.sqrt((dq * dq).sum(-1))),
        "action_rate": action_rate(action, last_action),
        "collision": collisions(s, frame or BaseFrame(s)),
        "joint_limits": joint_limit_excess(s.arm_q),
        "fall": g.fell.float(),
        "gripper_toggle": (((p > 0.5) != (last_action[..., 7] > 0.5)) & ~g.grasped).float(),
        "object_tilt": torch.where(g.grasped.any(1, keepdim=True), 0.0, box(1 - s.box_rot[:, 2, 2])),
        "base_approach": torch.where(far, towards.clamp(-1.0, 1.0), 0.0),
        "base_stance": torch.where(unheld, stance, 0.0),
    }
    return torch.stack([terms[n] for n in REWARD_TERMS], -1)


def _grasp_pose_dist(g: Geometry, grasp_pose: str) -> torch.Tensor:
    if grasp_pose == "height":
        return g.ee_handle[..., 2].abs()
    if grasp_pose == "bar":
        return g.bar_dist
    raise ValueError(f"grasp_pose must be one of {GRASP_POSES}, got {grasp_pose!r}")


def action_rate(action: torch.Tensor, last_action: torch.Tensor) -> torch.Tensor:
    """Squared action change per robot [N, R], each dim scaled by its half range."""
    return (((action - last_action) * _INV_SCALE) ** 2).sum(-1)


def joint_limit_excess(arm_q: torch.Tensor) -> torch.Tensor:
    """Summed excess of the arm joints beyond 95 % of their ranges [N, R]."""
    return torch.clamp((arm_q - _MID).abs() - _HALF95, min=0.0).sum(-1)


def collisions(s: PnPState, frame: BaseFrame | None = None) -> torch.Tensor:
    """Proxy for trunk/leg-box and robot-robot contact, per robot: 1.0 while its footprint
    rectangle (:data:`FOOTPRINT_HALF`) overlaps the box's (its yaw and edges) or the other
    robot's. Rectangles, not circles: beside a 1.5 m box a bounding circle covers the spot
    a robot must stand on to reach a handle."""
    frame = frame or BaseFrame(s)
    fx, fy = FOOTPRINT_HALF
    # The box in each robot's base frame: centre and x axis (a yawed rectangle).
    bx, by, _ = frame.point_xyz(*s.box_pos[:, None].unbind(-1))  # [N, R]
    ux, uy = frame.rotate_xy(s.box_rot[:, None, 0, 0], s.box_rot[:, None, 1, 0])
    n = torch.hypot(ux, uy).clamp(min=1e-6)
    hit = rects_overlap(bx, by, ux / n, uy / n, s.box_size[:, None, 0] / 2, s.box_size[:, None, 1] / 2, fx, fy)
    if s.base.shape[1] == 2:
        other = lambda x: x.flip(1)  # noqa: E731
        ox, oy, _ = frame.point_xyz(other(s.base[..., 0]), other(s.base[..., 1]), frame.oz)
        dyaw = other(s.base[..., 2]) - s.base[..., 2]
        hit = hit | rects_overlap(ox, oy, torch.cos(dyaw), torch.sin(dyaw), fx, fy, fx, fy)
    return hit.float()


def default_reward(terms: torch.Tensor) -> torch.Tensor:
    """The env's own reward with no curriculum: every term at mu_j (stage-dependent ones off)."""
    return terms @ _DEFAULT_MU.to(terms.dtype)
