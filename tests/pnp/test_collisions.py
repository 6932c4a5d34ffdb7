"""The collision proxy (pnp.task.collisions): footprint rectangles against the box and each other."""
import math

import torch

import pnp.task as T
from pnp.task import PnPState


def _state(bases, box_xy_yaw, box_size=(1.5, 0.45, 0.35)) -> PnPState:
    N, R = 1, len(bases)
    bx, by, yaw = box_xy_yaw
    c, s = math.cos(yaw), math.sin(yaw)
    z = torch.zeros
    return PnPState(
        base=torch.tensor([bases], dtype=torch.float32), base_z=torch.full((N, R), 0.59), base_vel=z(N, R, 3),
        arm_q=z(N, R, 6), arm_qd=z(N, R, 6), finger_q=z(N, R, 2), touch=z(N, R, 2, dtype=torch.bool),
        ee_pos=z(N, R, 3), ee_rot=torch.eye(3).expand(N, R, 3, 3), box_pos=torch.tensor([[bx, by, 0.2]]),
        box_rot=torch.tensor([[[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]]), box_vel=z(N, 6),
        box_size=torch.tensor([box_size]), goal=z(N, 2), init_goal_dist=torch.ones(N), grasp_cmd=z(N, R),
    )


def test_robot_box_overlap_follows_the_rectangles():
    fx, fy = T.FOOTPRINT_HALF
    hit = lambda *box: T.collisions(_state([[0.0, 0.0, 0.0]], box))[0, 0].item()  # noqa: E731
    assert hit(fx + 0.75 - 0.01, 0.0, 0.0) == 1.0 and hit(fx + 0.75 + 0.01, 0.0, 0.0) == 0.0
    # Turned 90 degrees the 1.5 m box is 0.45 m deep along x: a robot fits much closer.
    assert hit(fx + 0.225 + 0.01, 0.0, math.pi / 2) == 0.0 and hit(fx + 0.2, 0.0, math.pi / 2) == 1.0
    # Beside the far end of a long box: the bounding circle (radius 0.79 m) would call this a hit.
    assert hit(0.0, fy + 0.225 + 0.01, 0.0) == 0.0
    # A 45-degree box whose corner points at the robot's corner: bounding boxes overlap, shapes do not.
    corner = (fx + 0.25, fy + 0.25, math.pi / 4)
    assert T.collisions(_state([[0.0, 0.0, 0.0]], corner, (0.4, 0.4, 0.3)))[0, 0] == 0.0


def test_robot_robot_overlap_is_symmetric():
    fx, fy = T.FOOTPRINT_HALF
    far_box = (10.0, 10.0, 0.0)
    side = lambda gap: T.collisions(_state([[0.0, 0.0, 0.0], [0.0, 2 * fy + gap, 0.0]], far_box))[0]  # noqa: E731
    assert side(0.05).tolist() == [0.0, 0.0] and side(-0.05).tolist() == [1.0, 1.0]
    crossed = T.collisions(_state([[0.0, 0.0, 0.0], [fx + fy - 0.05, 0.0, math.pi / 2]], far_box))[0]
    assert crossed.tolist() == [1.0, 1.0]
