"""The observations of pick-and-place: named blocks per robot, spatial ones in its base
frame (:data:`OBS_BLOCKS`, fields in :data:`OBS_FIELDS`)."""
from __future__ import annotations

import torch

from pnp.sim.robot import FINGER_STROKE
from pnp.task.geometry import BaseFrame, Geometry, handles, stack_columns
from pnp.task.state import PnPState

# Order of the two handles in the object block (``own_*`` are ours, not the paper's):
# ``identity`` handle 0 then 1; ``own_first`` / ``own_last`` the robot's handle (geometry's)
# first / last. Why: the one-robot policy warm-started into the dual task went to handle 1
# in 100 % of its episodes, so two of them met at one handle (90 % of steps, no joint grasp
# in 371 iterations); listed last, a robot's own handle is where that habit takes it.
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
    small = stack_columns([*frame.rotate_xy(s.base_vel[..., 0], s.base_vel[..., 1]), s.base_vel[..., 2], *ee,
                           torch.sin(ee_yaw), torch.cos(ee_yaw), opening, *touch], N, R)
    return torch.cat([small[..., :3], s.arm_q, s.arm_qd * 0.1, small[..., 3:], last_action], -1)


def observations(s: PnPState, g: Geometry, last_action: torch.Tensor, frame: BaseFrame | None = None,
                 handle_order: str = "identity") -> dict[str, torch.Tensor]:
    """Named observation blocks [N, R, k] (sizes in :data:`OBS_BLOCKS`).

    ``handle_order``: ``identity`` lists handle 0 then 1; ``own_first`` / ``own_last`` list
    the robot's handle (``pnp.task.geometry.geometry``'s, the one its handle terms reward)
    first / last (see :data:`HANDLE_ORDERS`).
    """
    # Built from [N, R] / [N, 1] component columns, stacked once per block.
    frame = frame or BaseFrame(s)
    N, R = s.ee_pos.shape[:2]
    ee = frame.point_xyz(*s.ee_pos.unbind(-1))
    opening, touch = _opening(s), s.touch.float().unbind(-1)
    ego = ego_block(s, frame, last_action, ee, opening, touch)
    gx, gy = frame.rotate_xy(s.goal[:, None, 0] - frame.ox, s.goal[:, None, 1] - frame.oy)
    goal = stack_columns([gx, gy, torch.hypot(gx, gy)], N, R)
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
    obj = stack_columns([
        *frame.point_xyz(*s.box_pos[:, None].unbind(-1)), *axes_vel, *h_b[0], *h_b[1],
        *(a - b for a, b in zip(h_b[0], ee)), *(a - b for a, b in zip(h_b[1], ee)), *s.box_size[:, None].unbind(-1),
    ], N, R)
    if R == 2:
        other = lambda x: x.flip(1)  # noqa: E731  the other robot's value; flip [N, 2] columns, not [N, 2, 3]
        bx, by, byaw = s.base.unbind(-1)
        dyaw = other(byaw) - byaw
        neigh = stack_columns([
            *frame.rotate_xy(other(bx) - frame.ox, other(by) - frame.oy), torch.sin(dyaw), torch.cos(dyaw),
            *frame.point_xyz(*(other(x) for x in s.ee_pos.unbind(-1))), other(opening), *(other(t) for t in touch),
        ], N, R)
    else:
        neigh = torch.zeros(N, R, OBS_BLOCKS["neighbour"], dtype=ego.dtype)
    return {"ego": ego, "goal": goal, "object": obj, "neighbour": neigh}
