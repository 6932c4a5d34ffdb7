"""The pick-and-place task as batched torch functions of a state: observations, Table II
reward terms and stage-transition conditions. Shared by every backend.

Shapes: N worlds, R robots. Spatial observations are in each robot's base frame.

Written for CPU speed at thousands of worlds: rotations are spelled out elementwise (batched
3x3 matmuls of tiny matrices are slow on CPU), and there are no gathers, argmins, norms or
max(dim) over dims of size 2-3 and no per-call ``torch.tensor`` of constants. The plain
matmul/gather formulation is kept in ``tests/pnp/_task_reference.py``; the outputs are
checked equal by ``tests/pnp/test_task_equivalence.py``.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from pnp.box import HANDLE_HEIGHT, HANDLE_INSET, HANDLE_LEN
from pnp.kinematics import LW, REACH_MAX, REACH_MIN, SHOULDER
from pnp.robot import ARM_DEFAULT, ARM_RANGES, FINGER_STROKE
from pnp.scene import GOAL_RADIUS
from pnp.terms import CONDITIONS, REWARD_TABLE, REWARD_TERMS, STAGE_GATES, STAGE_PROGRESS_TERM

HL_DT = 0.1  # s, HL policy at 10 Hz
EPISODE_S = 45.0  # s, paper's time limit
MAX_OBJ_HEIGHT = 0.3  # m, "max height" of Table II's object height / drop terms
LIFT_HEIGHT = 0.1  # m, box bottom above the floor for "object lifted"
ON_FLOOR = 0.03  # m, box bottom below this counts as on the floor
READY_XY = 0.05  # m, EE horizontally within this of its handle for "gripper ready"
READY_Z = (-0.03, 0.25)  # m, EE height above the handle axis for "gripper ready"
READY_ALIGN = 0.9  # |cos| of the gripper-handle angle for "gripper ready"
GRASP_DIST = 0.035  # m, EE to the handle bar for a grasp
FALL_HEIGHT = 0.35  # m, base below this counts as a fall
# Half extents (base x, y) of a robot's standing footprint, trunk and legs: feet at
# x = +-0.41 m, leg capsules to y = +-0.16 m (pnp.robot), plus ~4 cm of margin.
FOOTPRINT_HALF = (0.45, 0.20)

# Action per robot (8-D), units: m/s, m/s, rad/s, m, m, m, rad, probability.
ACTION_NAMES = ("base_vx", "base_vy", "base_wz", "ee_x", "ee_y", "ee_z", "ee_yaw", "grasp")
ACTION_LOW = (-1.0, -0.5, -1.0, 0.3, -0.6, -0.55, -1.5708, 0.0)
ACTION_HIGH = (1.0, 0.5, 1.0, 1.3, 0.6, 0.35, 1.5708, 1.0)
# Order of the two handles in the object block (``own_*`` are ours, not the paper's):
# ``identity`` handle 0 then 1; ``own_first`` / ``own_last`` the robot's handle (geometry's)
# first / last. Why: the one-robot policy warm-started into the dual task went to handle 1
# in 100 % of its episodes, so two of them met at one handle (90 % of steps, no joint grasp
# in 371 iterations); listed last, a robot's own handle is where that habit takes it (stop 16).
HANDLE_ORDERS = ("identity", "own_first", "own_last")
OBS_BLOCKS = {"ego": 31, "goal": 3, "object": 30, "neighbour": 10}
# Fields inside each block (slices), for scripted policies and per-field saliency.
OBS_FIELDS = {
    "ego": {"base_vel": slice(0, 3), "arm_q": slice(3, 9), "arm_qd": slice(9, 15), "ee_pos": slice(15, 18),
            "ee_yaw_sincos": slice(18, 20), "gripper_opening": slice(20, 21), "pad_touch": slice(21, 23),
            "last_action": slice(23, 31)},
    "goal": {"goal_xy": slice(0, 2), "goal_dist": slice(2, 3)},
    "object": {"box_pos": slice(0, 3), "box_x_axis": slice(3, 6), "box_y_axis": slice(6, 9), "box_lin_vel": slice(9, 12),
               "box_ang_vel": slice(12, 15), "handles": slice(15, 21), "handles_from_ee": slice(21, 27),
               "box_size": slice(27, 30)},
    "neighbour": {"base_xy": slice(0, 2), "yaw_sincos": slice(2, 4), "ee_pos": slice(4, 7), "gripper_opening": slice(7, 8),
                  "pad_touch": slice(8, 10)},
}


@dataclass
class PnPState:
    """Everything the task functions need, as float32 tensors (world frame)."""

    base: torch.Tensor  # [N, R, 3] x, y, yaw
    base_z: torch.Tensor  # [N, R] trunk height
    base_vel: torch.Tensor  # [N, R, 3] vx, vy (world), yaw rate
    arm_q: torch.Tensor  # [N, R, 6]
    arm_qd: torch.Tensor  # [N, R, 6]
    finger_q: torch.Tensor  # [N, R, 2] opening of each finger
    touch: torch.Tensor  # [N, R, 2] bool, pad in contact
    ee_pos: torch.Tensor  # [N, R, 3]
    ee_rot: torch.Tensor  # [N, R, 3, 3]
    box_pos: torch.Tensor  # [N, 3]
    box_rot: torch.Tensor  # [N, 3, 3]
    box_vel: torch.Tensor  # [N, 6] linear, angular (world)
    box_size: torch.Tensor  # [N, 3] full edges
    goal: torch.Tensor  # [N, 2]
    init_goal_dist: torch.Tensor  # [N]
    grasp_cmd: torch.Tensor  # [N, R] gripper command executed (closes above 0.5)


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


def yaw_rotation(yaw: torch.Tensor) -> torch.Tensor:
    c, s = torch.cos(yaw), torch.sin(yaw)
    z, o = torch.zeros_like(yaw), torch.ones_like(yaw)
    return torch.stack([torch.stack([c, -s, z], -1), torch.stack([s, c, z], -1), torch.stack([z, z, o], -1)], -2)


class BaseFrame:
    """Each robot's base frame (yaw about z at the trunk), applied without matmuls.

    Built once per step and shared by :func:`reward_terms` and :func:`observations`. The
    ``*_xyz`` methods take and return components ([N, R] tensors, or [N, 1] per world):
    elementwise ops on those avoid the slow CPU paths of ops broadcasting over tiny dims.
    """

    def __init__(self, s: PnPState):
        yaw = s.base[..., 2]
        self.c, self.s = torch.cos(yaw), torch.sin(yaw)  # [N, R]
        self.ox, self.oy, self.oz = s.base[..., 0], s.base[..., 1], s.base_z

    def rotate_xy(self, x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """World vector components (x, y) -> base frame (z is unchanged by a yaw)."""
        return self.c * x + self.s * y, self.c * y - self.s * x

    def point_xyz(self, x, y, z) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """World point components -> base frame: R^T (p - origin)."""
        bx, by = self.rotate_xy(x - self.ox, y - self.oy)
        return bx, by, z - self.oz

    def point(self, p: torch.Tensor) -> torch.Tensor:
        """World points ``p`` [N, R (or 1), ..., 3] -> [N, R, ..., 3]."""
        extra = p.dim() - 3
        c, s, ox, oy, oz = (t.reshape(t.shape + (1,) * extra) for t in (self.c, self.s, self.ox, self.oy, self.oz))
        dx, dy, dz = p[..., 0] - ox, p[..., 1] - oy, p[..., 2] - oz
        return torch.stack([c * dx + s * dy, c * dy - s * dx, dz], -1)


def _dot(a, b):
    """Dot product of 3-vectors given as components (no reduction over a dim of 3)."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _stack(cols, N: int, R: int) -> torch.Tensor:
    """Columns ([N, R] or per world [N, 1]) -> [N, R, K]."""
    return torch.stack([c.expand(N, R) for c in cols], -1)


def to_base(s: PnPState, p: torch.Tensor) -> torch.Tensor:
    """World points ``p`` [N, R, ..., 3] into each robot's base frame."""
    return BaseFrame(s).point(p)


def handles(s: PnPState) -> torch.Tensor:
    """Handle bar centres [N, 2, 3] in the world frame."""
    x = (s.box_size[:, 0] / 2 - HANDLE_INSET).unsqueeze(-1)
    z = (s.box_size[:, 2] / 2 + HANDLE_HEIGHT).unsqueeze(-1)
    # box_pos + R @ (+-x, 0, z), with the columns of R (box axes) spelled out.
    centre = s.box_pos + z * s.box_rot[:, :, 2]
    off = x * s.box_rot[:, :, 0]
    return torch.stack([centre + off, centre - off], 1)


@dataclass
class Geometry:
    """Per-robot quantities every reward and condition uses (computed once per step)."""

    handle: torch.Tensor  # [N, R, 3] the robot's handle: nearest its EE, or its claim
    own: torch.Tensor  # [N, R] bool, True where its handle is handle 1
    ee_handle: torch.Tensor  # [N, R, 3] handle - EE
    align: torch.Tensor  # [N, R] |cos| of the gripper-handle angle
    bar_dist: torch.Tensor  # [N, R] EE distance to the handle bar (segment)
    grasped: torch.Tensor  # [N, R] bool
    box_lift: torch.Tensor  # [N] box bottom above the floor
    box_goal_dist: torch.Tensor  # [N]
    box_in_goal: torch.Tensor  # [N] bool
    box_on_floor: torch.Tensor  # [N] bool
    fell: torch.Tensor  # [N, R] bool


def geometry(s: PnPState, claim: torch.Tensor | None = None) -> Geometry:
    """Task geometry; ``claim`` [N, R] (handle index, -1 for none) overrides the nearest-handle
    rule where set (see :func:`update_claims`)."""
    N, R = s.ee_pos.shape[:2]
    h = handles(s)  # [N, 2, 3]
    # Vectors as components; world quantities are [N, 1] columns broadcasting over robots.
    ee = s.ee_pos.unbind(-1)
    h0, h1 = h[:, None, 0].unbind(-1), h[:, None, 1].unbind(-1)
    d0 = [a - b for a, b in zip(h0, ee)]
    d1 = [a - b for a, b in zip(h1, ee)]
    dd0, dd1 = _dot(d0, d0), _dot(d1, d1)
    k1 = dd1 < dd0  # strict: ties pick handle 0, as argmin does
    if R == 2:
        # A robot's handle is its nearest, unless the other robot is nearer to that one:
        # then it is the other handle (the other robot's ties win). Who takes which is
        # still the policies' choice (whoever comes closer first), but the second robot's
        # handle terms now lead it to the free handle; with the nearest for both, two
        # warm-started robots settled on one handle (kinematic backend, 2026-11-24).
        own = torch.where(k1, dd1, dd0)
        conflict = (k1[:, 0] == k1[:, 1]).unsqueeze(1)
        k1 = k1 ^ (conflict & torch.stack([own[:, 0] > own[:, 1], own[:, 1] >= own[:, 0]], 1))
    if claim is not None:
        k1 = torch.where(claim >= 0, claim == 1, k1)
    ee_handle = [torch.where(k1, a, b) for a, b in zip(d1, d0)]
    handle = _stack([torch.where(k1, a, b) for a, b in zip(h1, h0)], N, R)
    bar_axis = s.box_rot[:, None, :, 1].unbind(-1)  # box y axis
    # Aligned when the gripper's closing axis (its y) is perpendicular to the bar.
    align = 1.0 - _dot(s.ee_rot[..., :, 1].unbind(-1), bar_axis).abs()
    half_len = torch.clamp(0.6 * s.box_size[:, 1], max=HANDLE_LEN).unsqueeze(1) / 2
    along = _dot(ee_handle, bar_axis)
    perp = [e - along * b for e, b in zip(ee_handle, bar_axis)]
    excess = torch.clamp(along.abs() - half_len, min=0.0)
    bar_dist = torch.sqrt(_dot(perp, perp) + excess * excess)
    grasped = (s.grasp_cmd > 0.5) & s.touch[..., 0] & s.touch[..., 1] & (bar_dist < GRASP_DIST)
    # Half extent of the (possibly tilted) box along world z: row 2 of 0.5 |R| @ size.
    bottom = s.box_pos[:, 2] - 0.5 * _dot(s.box_rot[:, 2].abs().unbind(-1), s.box_size.unbind(-1))
    gd = torch.hypot(s.box_pos[:, 0] - s.goal[:, 0], s.box_pos[:, 1] - s.goal[:, 1])
    return Geometry(
        handle=handle, own=k1, ee_handle=torch.stack(ee_handle, -1), align=align, bar_dist=bar_dist, grasped=grasped,
        box_lift=bottom, box_goal_dist=gd, box_in_goal=gd < GOAL_RADIUS, box_on_floor=bottom < ON_FLOOR,
        fell=s.base_z < FALL_HEIGHT,
    )


def update_claims(claim: torch.Tensor, g: Geometry) -> torch.Tensor:
    """Claims after this step (ours, not in the paper; ``env.handle_claim``): a robot without
    one (just reset) claims the handle :func:`geometry` gives it, and keeps it for the episode.
    Why: a handle order that follows the nearest handle feeds back into the policy; listed
    nearest-first, the one-robot policy's nearest handle flipped 13399 times in 38400
    robot-steps (218 under identity order) and it got "ready" in 0.8 % of worlds. And two
    robots at one handle swapped it as each came nearer (stop 16). Who takes which is then
    set by where the robots start (the farther of two at one handle takes the other), not
    chosen later."""
    return torch.where(claim >= 0, claim, g.own.long())


def stage_conditions(s: PnPState, g: Geometry, held_ready: bool | None = None) -> torch.Tensor:
    """Bool [N, R, len(CONDITIONS)]; column i is the condition of edge S_i -> S_{i+1}.
    ``held_ready`` (default: with two robots) counts a gripper that holds its handle as ready."""
    dz = -g.ee_handle[..., 2]  # EE above the handle axis
    xy = torch.hypot(g.ee_handle[..., 0], g.ee_handle[..., 1])
    ready = (xy < READY_XY) & (dz > READY_Z[0]) & (dz < READY_Z[1]) & (g.align > READY_ALIGN)
    if held_ready is None:
        held_ready = s.ee_pos.shape[1] == 2
    if held_ready:
        # Ours: grasps along the bar, off its centre, left two dual robots carrying the box
        # home in S0 (stop 17), and the curriculum, seeing no stage past S3, faded the placing
        # terms. Not for one robot: there it cut the fast learning test's mean end stage
        # from 0.85 to 0.0 (seed 0).
        ready = ready | g.grasped
    # Box conditions are [N, 1] and broadcast over the robots.
    lift = (g.box_lift > LIFT_HEIGHT).unsqueeze(1)
    in_goal = g.box_in_goal.unsqueeze(1)
    placed_box = (g.box_on_floor & g.box_in_goal).unsqueeze(1)
    lifted = g.grasped & lift
    on_goal = lifted & in_goal
    placed = g.grasped & placed_box
    released = ~g.grasped & (s.grasp_cmd < 0.5) & placed_box
    out = torch.stack([ready, g.grasped, lifted, on_goal, placed, released], -1)
    assert out.shape[-1] == len(CONDITIONS)
    return out


def reward_terms(s: PnPState, g: Geometry, action: torch.Tensor, last_action: torch.Tensor, cond: torch.Tensor,
                 frame: BaseFrame | None = None) -> torch.Tensor:
    """Float [N, R, len(REWARD_TERMS)] in the order of ``pnp.terms.REWARD_TERMS``."""
    R = s.ee_pos.shape[1]
    box = lambda x: x.unsqueeze(1).expand(-1, R)  # noqa: E731
    p = action[..., 7]  # the policy's grasp probability (Table II's grab action terms)
    height = torch.clamp(g.box_lift, 0.0, MAX_OBJ_HEIGHT)
    tx, ty = s.goal[:, 0] - s.box_pos[:, 0], s.goal[:, 1] - s.box_pos[:, 1]
    v_goal = (s.box_vel[:, 0] * tx + s.box_vel[:, 1] * ty) / torch.hypot(tx, ty).clamp(min=1e-6)
    dq = s.arm_q - _ARM_DEFAULT
    terms = {
        "gripper_ready_pose": torch.exp(-3 * torch.hypot(g.ee_handle[..., 0], g.ee_handle[..., 1])) * g.align,
        "gripper_grasp_pose": torch.exp(-10 * g.ee_handle[..., 2].abs()) * g.align,
        "object_grabbed": g.grasped.float(),
        "grab_action": torch.where(g.grasped, p, 1 - p),
        "object_height": box(height),
        "object_to_goal_vel": box(torch.clamp(1 - torch.exp(-2 * v_goal), -1.0, 1.0)),
        "object_to_goal_dist": box(torch.exp(-2 * g.box_goal_dist / s.init_goal_dist.clamp(min=1e-3))),
        "object_drop": box(MAX_OBJ_HEIGHT - height),
        "grab_action_in_range": torch.clamp(0.5 - p, min=0.0),
        "object_released_in_goal": cond[..., 5].float(),
        "stage_progress": torch.zeros_like(p),
        "arm_default_pose": torch.exp(-2 * torch.sqrt((dq * dq).sum(-1))),
        "action_rate": action_rate(action, last_action),
        "collision": _collisions(s, frame or BaseFrame(s)),
        "joint_limits": joint_limit_excess(s.arm_q),
        "fall": g.fell.float(),
        "ee_out_of_reach": ee_out_of_reach(action[..., 3:6]),
    }
    return torch.stack([terms[n] for n in REWARD_TERMS], -1)


def action_rate(action: torch.Tensor, last_action: torch.Tensor) -> torch.Tensor:
    """Squared action change per robot [N, R], each dim scaled by its half range."""
    return (((action - last_action) * _INV_SCALE) ** 2).sum(-1)


def ee_out_of_reach(ee_cmd: torch.Tensor) -> torch.Tensor:
    """Distance [N, R] from EE commands [N, R, 3] to :func:`pnp.kinematics.clamp_reach` of
    them: the clamp moves the wrist centre radially about the shoulder, so it is the radial
    excess of the wrist centre outside [REACH_MIN, REACH_MAX]."""
    wx, wy, wz = ee_cmd[..., 0] - SHOULDER[0], ee_cmd[..., 1] - SHOULDER[1], ee_cmd[..., 2] - SHOULDER[2] + LW
    n = torch.sqrt(wx * wx + wy * wy + wz * wz)
    return torch.clamp(n - REACH_MAX, min=0.0) + torch.clamp(REACH_MIN - n, min=0.0)


def joint_limit_excess(arm_q: torch.Tensor) -> torch.Tensor:
    """Summed excess of the arm joints beyond 95 % of their ranges [N, R]."""
    return torch.clamp((arm_q - _MID).abs() - _HALF95, min=0.0).sum(-1)


def _collisions(s: PnPState, frame: BaseFrame | None = None) -> torch.Tensor:
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


def rects_overlap(cx, cy, ux, uy, hu, hv, fx: float, fy: float) -> torch.Tensor:
    """Separating-axis test of the rectangle centred at (cx, cy) with unit x axis (ux, uy)
    and half extents (hu, hv) against the axis-aligned one at the origin, half (fx, fy)."""
    cu, cv = cx * ux + cy * uy, cy * ux - cx * uy  # centre offset in the rectangle's axes
    au, av = ux.abs(), uy.abs()  # |cos|, |sin| of its yaw
    return ((cx.abs() <= fx + hu * au + hv * av) & (cy.abs() <= fy + hu * av + hv * au)
            & (cu.abs() <= hu + fx * au + fy * av) & (cv.abs() <= hv + fx * av + fy * au))


def _opening(s: PnPState) -> torch.Tensor:
    return (s.finger_q[..., 0] + s.finger_q[..., 1]) * (0.5 / FINGER_STROKE)


def ego_block(s: PnPState, frame: BaseFrame, last_action: torch.Tensor, ee=None, opening=None,
              touch=None) -> torch.Tensor:
    """The robot's own block [N, R, 31] (fields in ``OBS_FIELDS["ego"]``); any task with this
    robot reuses it. ``ee``/``opening``/``touch`` may be passed when the caller has them."""
    N, R = s.ee_pos.shape[:2]
    c, sn = frame.c, frame.s
    ee = ee if ee is not None else frame.point_xyz(*s.ee_pos.unbind(-1))
    opening = opening if opening is not None else _opening(s)
    touch = touch if touch is not None else s.touch.float().unbind(-1)
    # EE yaw in the base frame from column 1 of R_base^T @ ee_rot.
    e01, e11 = s.ee_rot[..., 0, 1], s.ee_rot[..., 1, 1]
    ee_yaw = torch.atan2(-(c * e01 + sn * e11), c * e11 - sn * e01)
    small = _stack([*frame.rotate_xy(s.base_vel[..., 0], s.base_vel[..., 1]), s.base_vel[..., 2], *ee,
                    torch.sin(ee_yaw), torch.cos(ee_yaw), opening, *touch], N, R)
    return torch.cat([small[..., :3], s.arm_q, s.arm_qd * 0.1, small[..., 3:], last_action], -1)


def observations(s: PnPState, g: Geometry, last_action: torch.Tensor, frame: BaseFrame | None = None,
                 handle_order: str = "identity") -> dict[str, torch.Tensor]:
    """Named observation blocks [N, R, k] (sizes in :data:`OBS_BLOCKS`).

    ``handle_order``: ``identity`` lists handle 0 then 1; ``own_first`` / ``own_last`` list
    the robot's handle (:func:`geometry`'s, the one its handle terms reward) first / last
    (see :data:`HANDLE_ORDERS`).
    """
    # Built from [N, R] / [N, 1] component columns, stacked once per block.
    frame = frame or BaseFrame(s)
    N, R = s.ee_pos.shape[:2]
    ee = frame.point_xyz(*s.ee_pos.unbind(-1))
    opening, touch = _opening(s), s.touch.float().unbind(-1)
    ego = ego_block(s, frame, last_action, ee, opening, touch)
    gx, gy = frame.rotate_xy(s.goal[:, None, 0] - frame.ox, s.goal[:, None, 1] - frame.oy)
    goal = _stack([gx, gy, torch.hypot(gx, gy)], N, R)
    h = handles(s)
    h_b = [frame.point_xyz(*h[:, None, k].unbind(-1)) for k in range(2)]
    axes_vel = []  # box x, y axes (columns of box_rot), linear and angular velocity
    for v in (s.box_rot[:, None, :, 0], s.box_rot[:, None, :, 1], s.box_vel[:, None, :3], s.box_vel[:, None, 3:]):
        axes_vel += [*frame.rotate_xy(v[..., 0], v[..., 1]), v[..., 2]]
    if handle_order in ("own_first", "own_last"):
        # Listed as if the box were turned half a turn about its z axis (it is symmetric), so
        # the listing stays a real box pose: its x axis points at the first-listed handle.
        swap = g.own if handle_order == "own_first" else ~g.own
        h_b = [[torch.where(swap, b, a) for a, b in zip(*h_b)], [torch.where(swap, a, b) for a, b in zip(*h_b)]]
        axes_vel[:6] = [torch.where(swap, -a, a) for a in axes_vel[:6]]
    elif handle_order != "identity":
        raise ValueError(f"handle_order must be one of {HANDLE_ORDERS}, got {handle_order!r}")
    obj = _stack([
        *frame.point_xyz(*s.box_pos[:, None].unbind(-1)), *axes_vel, *h_b[0], *h_b[1],
        *(a - b for a, b in zip(h_b[0], ee)), *(a - b for a, b in zip(h_b[1], ee)), *s.box_size[:, None].unbind(-1),
    ], N, R)
    if R == 2:
        other = lambda x: x.flip(1)  # noqa: E731  the other robot's value; flip [N, 2] columns, not [N, 2, 3]
        bx, by, byaw = s.base.unbind(-1)
        dyaw = other(byaw) - byaw
        neigh = _stack([
            *frame.rotate_xy(other(bx) - frame.ox, other(by) - frame.oy), torch.sin(dyaw), torch.cos(dyaw),
            *frame.point_xyz(*(other(x) for x in s.ee_pos.unbind(-1))), other(opening), *(other(t) for t in touch),
        ], N, R)
    else:
        neigh = torch.zeros(N, R, OBS_BLOCKS["neighbour"], dtype=ego.dtype)
    return {"ego": ego, "goal": goal, "object": obj, "neighbour": neigh}


def default_reward(terms: torch.Tensor) -> torch.Tensor:
    """The env's own reward with no curriculum: every term at mu_j (stage-dependent ones off)."""
    return terms @ _DEFAULT_MU.to(terms.dtype)
