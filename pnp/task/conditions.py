"""The stage-transition conditions of pick-and-place (``pnp.task.terms.CONDITIONS``), per robot,
from the task geometry."""
from __future__ import annotations

import torch

from pnp.task.geometry import Geometry
from pnp.task.state import PnPState
from pnp.task.terms import CONDITIONS

LIFT_HEIGHT = 0.1  # m, box bottom above the floor for "object lifted"
READY_XY = 0.05  # m, EE horizontally within this of its handle for "gripper ready"
READY_Z = (-0.03, 0.25)  # m, EE height above the handle axis for "gripper ready"
READY_ALIGN = 0.9  # |cos| of the gripper-handle angle for "gripper ready"


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
        # home in S0, and the curriculum, seeing no stage past S3, faded the placing terms.
        # Not for one robot: there it cut the fast learning test's mean end stage from 0.85
        # to 0.0 (seed 0).
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
