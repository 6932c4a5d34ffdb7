"""What every pick-and-place task function reads: the state of N worlds with R robots
(:class:`PnPState`), the action layout and the task's clock. Every backend produces this
state; ``pnp.task`` lists the functions of it."""
from __future__ import annotations

from dataclasses import dataclass

import torch

HL_DT = 0.1  # s, HL policy at 10 Hz
EPISODE_S = 45.0  # s, paper's time limit

# Action per robot (8-D), units: m/s, m/s, rad/s, m, m, m, rad, probability.
ACTION_NAMES = ("base_vx", "base_vy", "base_wz", "ee_x", "ee_y", "ee_z", "ee_yaw", "grasp")
ACTION_LOW = (-1.0, -0.5, -1.0, 0.3, -0.6, -0.55, -1.5708, 0.0)
ACTION_HIGH = (1.0, 0.5, 1.0, 1.3, 0.6, 0.35, 1.5708, 1.0)


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
