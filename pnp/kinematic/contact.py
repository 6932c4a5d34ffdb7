"""Robot-box pushes of the kinematic model (``KinematicParams.box_pushed``): on MuJoCo a
resting box is shoved by the legs and by the gripper's pads; the kinematic box otherwise
moves only when held, so a policy trained there walks its legs and sweeps its pads into
the box (measured: `docs/transfer_gap.md`, "Where the contacts differ"). Both pushes move the
box by the penetration, in the plane (no yaw, no tipping): a minimum-translation stand-in
for contact, not a dynamics model."""
from __future__ import annotations

import torch

from pnp.sim.box import HANDLE_RADIUS
from pnp.sim.robot import PAD_HALF
from pnp.task.geometry import FOOTPRINT_HALF

# Each pad as three spheres along its width (it is 7 cm wide, 1.6 cm thick, 3 cm tall);
# its vertical half height beyond the sphere radius is taken off the height gap.
_PAD_R = PAD_HALF[1]
_PAD_OFFSETS = (-PAD_HALF[2] + _PAD_R, 0.0, PAD_HALF[2] - _PAD_R)
_PAD_DZ = PAD_HALF[0] - _PAD_R
MAX_PUSH = 0.1  # m per HL step: a bound on one step's shove (~1 m/s, the base's speed)


def leg_push(st: dict[str, torch.Tensor], bx: torch.Tensor, by: torch.Tensor, yaw: torch.Tensor
             ) -> tuple[torch.Tensor, torch.Tensor]:
    """[N] box shift (x, y) that takes the box out of every footprint at (bx, by, yaw) [N, R]:
    per robot the separating-axis minimum translation, summed over robots."""
    fx, fy = FOOTPRINT_HALF
    c, s = torch.cos(yaw), torch.sin(yaw)
    bc, bs = st["box_c"].unsqueeze(1), st["box_s"].unsqueeze(1)
    hu, hv = st["box_size"][:, 0:1] * 0.5, st["box_size"][:, 1:2] * 0.5
    dx, dy = st["box_x"].unsqueeze(1) - bx, st["box_y"].unsqueeze(1) - by
    best = torch.full_like(dx, float("inf"))
    px, py = torch.zeros_like(dx), torch.zeros_like(dx)
    inside = torch.ones_like(dx, dtype=torch.bool)
    for nx, ny in ((c, s), (-s, c), (bc.expand_as(c), bs.expand_as(c)), (-bs.expand_as(c), bc.expand_as(c))):
        foot = fx * (c * nx + s * ny).abs() + fy * (c * ny - s * nx).abs()
        box = hu * (bc * nx + bs * ny).abs() + hv * (bc * ny - bs * nx).abs()
        d = dx * nx + dy * ny
        depth = foot + box - d.abs()
        inside = inside & (depth > 0)
        take = depth < best
        sign = torch.where(d >= 0, 1.0, -1.0)
        best = torch.where(take, depth, best)
        px, py = torch.where(take, sign * depth * nx, px), torch.where(take, sign * depth * ny, py)
    return (px * inside).sum(1), (py * inside).sum(1)


def pad_push(st: dict[str, torch.Tensor], ee_x: torch.Tensor, ee_y: torch.Tensor, ee_z: torch.Tensor,
             cg: torch.Tensor, sg: torch.Tensor, finger: torch.Tensor, active: torch.Tensor
             ) -> tuple[torch.Tensor, torch.Tensor]:
    """[N] box shift (x, y) from the pads of the ``active`` grippers [N, R] (EE at ee_*, yaw
    (cg, sg), each finger ``finger`` m open) pressing into either handle bar: each pad sphere
    inside a bar pushes the box by its depth along the horizontal part of the contact normal."""
    ux, uy = -sg, cg  # closing axis (the fingers' slide axis, horizontal for a downward gripper)
    bc, bs = st["box_c"].unsqueeze(1), st["box_s"].unsqueeze(1)
    hx, half_len = st["box_hx"], st["box_half_len"]
    bar_z = (st["box_z"] + st["box_hz"]).unsqueeze(1)
    dz = ((ee_z - bar_z).abs() - _PAD_DZ).clamp(min=0.0)
    reach = HANDLE_RADIUS + _PAD_R
    sx, sy = torch.zeros_like(ee_x), torch.zeros_like(ee_x)
    for side in (1.0, -1.0):
        off = side * (finger + _PAD_R)
        for w in _PAD_OFFSETS:
            px, py = ee_x + off * ux + w * cg, ee_y + off * uy + w * sg  # sphere centre (world)
            rx, ry = px - st["box_x"].unsqueeze(1), py - st["box_y"].unsqueeze(1)
            lx, ly = bc * rx + bs * ry, bc * ry - bs * rx  # in the box frame
            ly_bar = ly.clamp(-half_len, half_len)  # nearest point on each bar's axis
            for bar_x in (hx, -hx):
                gx, gy = lx - bar_x, ly - ly_bar  # bar axis -> sphere, box frame
                dist = torch.sqrt(gx * gx + gy * gy + dz * dz).clamp(min=1e-6)
                depth = (reach - dist).clamp(min=0.0)
                # The box moves away from the sphere: along -(gx, gy), scaled to the depth.
                kx, ky = -gx / dist * depth, -gy / dist * depth
                sx, sy = sx + bc * kx - bs * ky, sy + bs * kx + bc * ky
    return (sx * active).sum(1), (sy * active).sum(1)


def clamp_push(px: torch.Tensor, py: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The shift (px, py) [N] shortened to at most ``MAX_PUSH``."""
    n = torch.sqrt(px * px + py * py)
    k = (MAX_PUSH / n.clamp(min=MAX_PUSH))
    return px * k, py * k
