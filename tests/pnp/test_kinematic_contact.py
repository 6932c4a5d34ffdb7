"""The kinematic model's robot-box pushes (pnp.kinematic.contact), on hand-made states."""
import math

import pytest
import torch

from pnp.sim.box import HANDLE_RADIUS
from pnp.kinematic.contact import MAX_PUSH, clamp_push, leg_push, pad_push
from pnp.sim.robot import PAD_HALF
from pnp.task.geometry import FOOTPRINT_HALF


def _box(x=0.0, y=0.0, yaw=0.0, size=(0.4, 0.3, 0.2), hx=0.25, half_len=0.1, hz=0.15):
    t = lambda v: torch.tensor([float(v)])  # noqa: E731
    return {"box_x": t(x), "box_y": t(y), "box_z": t(size[2] / 2), "box_c": t(math.cos(yaw)), "box_s": t(math.sin(yaw)),
            "box_size": torch.tensor([size], dtype=torch.float32), "box_hx": torch.tensor([[hx]]),
            "box_half_len": torch.tensor([[half_len]]), "box_hz": t(hz)}


def _pose(*v):
    return [torch.tensor([[float(a)]]) for a in v]


def test_leg_push_is_the_minimum_translation_out_of_the_footprint():
    st = _box(x=0.5, y=0.02)
    px, py = leg_push(st, *_pose(0.0, 0.0, 0.0))
    # x overlap 0.45 + 0.2 - 0.5 = 0.15, y overlap 0.2 + 0.15 - 0.02 = 0.33: out along +x.
    assert px.item() == pytest.approx(FOOTPRINT_HALF[0] + 0.2 - 0.5, abs=1e-6)
    assert py.item() == pytest.approx(0.0, abs=1e-6)
    # Behind the base it goes out backwards; turned by 90 degrees, sideways.
    px, _ = leg_push(_box(x=-0.5), *_pose(0.0, 0.0, 0.0))
    assert px.item() == pytest.approx(-0.15, abs=1e-6)
    px, py = leg_push(_box(y=0.5), *_pose(0.0, 0.0, math.pi / 2))
    assert (px.item(), py.item()) == pytest.approx((0.0, FOOTPRINT_HALF[0] + 0.15 - 0.5), abs=1e-6)


def test_no_leg_push_without_overlap():
    px, py = leg_push(_box(x=0.66), *_pose(0.0, 0.0, 0.0))
    assert px.item() == 0.0 and py.item() == 0.0


def test_open_gripper_around_a_bar_pushes_nothing_and_a_pad_in_it_pushes_away():
    st = _box()
    bar_z = st["box_z"].item() + st["box_hz"].item()
    # Gripper yaw pi/2: closing axis along world x, across the bar at x = +0.25.
    cg, sg = _pose(0.0, 1.0)
    open_ = torch.tensor([[0.07]])
    sx, sy = pad_push(st, *_pose(0.25, 0.0, bar_z), cg, sg, open_, torch.tensor([[True]]))
    assert sx.item() == 0.0 and sy.item() == 0.0
    # Moved 6 cm along +x: the -x pad (at 0.31 - 0.078 = 0.232) sits inside the bar (r 0.015).
    sx, sy = pad_push(st, *_pose(0.31, 0.0, bar_z), cg, sg, open_, torch.tensor([[True]]))
    pad_centre = 0.31 - (0.07 + PAD_HALF[1])
    depth = HANDLE_RADIUS + PAD_HALF[1] - abs(pad_centre - 0.25)
    # The pad came from -x: three spheres along its width, each pushing the bar on by the depth (+x).
    assert sx.item() == pytest.approx(3 * depth, abs=1e-5)
    assert sy.item() == pytest.approx(0.0, abs=1e-6)
    # An inactive gripper (it holds the box) pushes nothing; far above the bar neither.
    sx, _ = pad_push(st, *_pose(0.31, 0.0, bar_z), cg, sg, open_, torch.tensor([[False]]))
    assert sx.item() == 0.0
    sx, _ = pad_push(st, *_pose(0.31, 0.0, bar_z + 0.05), cg, sg, open_, torch.tensor([[True]]))
    assert sx.item() == 0.0


def test_clamp_push_bounds_one_step():
    px, py = clamp_push(torch.tensor([0.3, 0.01]), torch.tensor([0.4, 0.0]))
    assert torch.hypot(px, py)[0].item() == pytest.approx(MAX_PUSH)
    assert (px[1].item(), py[1].item()) == (pytest.approx(0.01), 0.0)
