"""Worlds, actions and frames shared by the kinematic backend's tests."""
import math

import torch

from pnp.sim.backend import Layout
from pnp.sim.box import SINGLE_ROBOT_BOXES
from pnp.sim.robot import STANDING_HEIGHT
from pnp.task import geometry


def _layout(n, robots, box=SINGLE_ROBOT_BOXES[0], box_xy=(0.85, 0.0), box_yaw=0.0, bases=None):
    bases = bases or [(0.0, 0.0, 0.0), (2.6, 0.0, math.pi)][:robots]
    return Layout(
        base=torch.tensor(bases, dtype=torch.float32).expand(n, robots, 3).clone(),
        box_xy_yaw=torch.tensor([*box_xy, box_yaw]).expand(n, 3).clone(),
        box_size=torch.tensor(box.size).expand(n, 3).clone(), box_mass=torch.full((n,), box.mass),
    )


def _action(n, robots, ee=(0.75, 0.0, -0.3), yaw=0.0, grasp=0.0, vx=0.0, wz=0.0):
    a = torch.zeros(n, robots, 8)
    a[..., 0], a[..., 2] = vx, wz
    a[..., 3:6] = torch.as_tensor(ee, dtype=torch.float32)
    a[..., 6] = torch.as_tensor(yaw, dtype=torch.float32)
    a[..., 7] = torch.as_tensor(grasp, dtype=torch.float32)
    return a


def _to_world(b, p_base, r=0):
    base = b.base[:, r]
    c, s = torch.cos(base[:, 2]), torch.sin(base[:, 2])
    p_base = p_base.expand(len(base), 3)
    x, y, z = p_base[..., 0], p_base[..., 1], p_base[..., 2]
    return torch.stack([base[:, 0] + c * x - s * y, base[:, 1] + s * x + c * y, z + STANDING_HEIGHT], -1)


def _handle_z_base(box):
    return box.size[2] + 0.06 - STANDING_HEIGHT  # bar axis height with the box on the floor, base frame


def _steps(b, act, n):
    for _ in range(n):
        b.step(act)


def _grasped(b, grasp_cmd):
    s = b.state(torch.zeros(b.num_worlds, 2), torch.ones(b.num_worlds), grasp_cmd)
    return geometry(s).grasped
