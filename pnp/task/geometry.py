"""Task geometry that the reward terms, stage conditions and observations share: each
robot's base frame, the handles, which handle is whose (:func:`geometry`,
:func:`update_claims`) and footprint overlap (:func:`rects_overlap`)."""
from __future__ import annotations

from dataclasses import dataclass

import torch

from pnp.sim.box import HANDLE_HEIGHT, HANDLE_INSET, HANDLE_LEN
from pnp.sim.scene import GOAL_RADIUS
from pnp.task.state import PnPState

ON_FLOOR = 0.03  # m, box bottom below this counts as on the floor
GRASP_DIST = 0.035  # m, EE to the handle bar for a grasp
FALL_HEIGHT = 0.35  # m, base below this counts as a fall
# Half extents (base x, y) of a robot's standing footprint, trunk and legs: feet at
# x = +-0.41 m, leg capsules to y = +-0.16 m (pnp.sim.robot), plus ~4 cm of margin.
FOOTPRINT_HALF = (0.45, 0.20)


def yaw_rotation(yaw: torch.Tensor) -> torch.Tensor:
    c, s = torch.cos(yaw), torch.sin(yaw)
    z, o = torch.zeros_like(yaw), torch.ones_like(yaw)
    return torch.stack([torch.stack([c, -s, z], -1), torch.stack([s, c, z], -1), torch.stack([z, z, o], -1)], -2)


class BaseFrame:
    """Each robot's base frame (yaw about z at the trunk), applied without matmuls.

    Built once per step and shared by the reward terms and the observations. The
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


def stack_columns(cols, N: int, R: int) -> torch.Tensor:
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
    handle = stack_columns([torch.where(k1, a, b) for a, b in zip(h1, h0)], N, R)
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
    robots at one handle swapped it as each came nearer. Who takes which is then set by
    where the robots start (the farther of two at one handle takes the other), not chosen
    later."""
    return torch.where(claim >= 0, claim, g.own.long())


def rects_overlap(cx, cy, ux, uy, hu, hv, fx: float, fy: float) -> torch.Tensor:
    """Separating-axis test of the rectangle centred at (cx, cy) with unit x axis (ux, uy)
    and half extents (hu, hv) against the axis-aligned one at the origin, half (fx, fy)."""
    cu, cv = cx * ux + cy * uy, cy * ux - cx * uy  # centre offset in the rectangle's axes
    au, av = ux.abs(), uy.abs()  # |cos|, |sin| of its yaw
    return ((cx.abs() <= fx + hu * au + hv * av) & (cy.abs() <= fy + hu * av + hv * au)
            & (cu.abs() <= hu + fx * au + fy * av) & (cv.abs() <= hv + fx * av + fy * au))
