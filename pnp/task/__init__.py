"""The pick-and-place task as batched torch functions of a state: observations, Table II
reward terms and stage-transition conditions. Shared by every backend.

Shapes: N worlds, R robots. Spatial observations are in each robot's base frame. One
module per concern; the state, geometry, condition, reward and observation functions are
importable from here:

* ``pnp.task.state``: the state every function reads (:class:`PnPState`), the action
  layout and the task's clock;
* ``pnp.task.geometry``: base frames, handles, which handle is whose, footprint overlap;
* ``pnp.task.conditions``: the stage-transition conditions;
* ``pnp.task.rewards``: the reward terms and the env's reward without a curriculum;
* ``pnp.task.observations``: the observation blocks;
* ``pnp.task.terms``: the one list of stage, condition and reward-term names;
* ``pnp.task.stage_graph``: the curriculum's stage transition graph;
* ``pnp.task.scripted``: a scripted policy on the observation blocks (a reference, and
  the roll-ins' driver);
* ``pnp.task.ee_tracking``, ``pnp.task.ee_scripted``: the 4-stage EE-tracking ablation and
  its scripted policy.

Written for CPU speed at thousands of worlds: rotations are spelled out elementwise (batched
3x3 matmuls of tiny matrices are slow on CPU), and there are no gathers, argmins, norms or
max(dim) over dims of size 2-3 and no per-call ``torch.tensor`` of constants. The plain
matmul/gather formulation is kept in ``tests/pnp/_task_reference.py``; the outputs are
checked equal by ``tests/pnp/test_task_equivalence.py``.
"""
from __future__ import annotations

from pnp.task.conditions import LIFT_HEIGHT, READY_ALIGN, READY_XY, READY_Z, stage_conditions
from pnp.task.geometry import (
    FALL_HEIGHT, FOOTPRINT_HALF, GRASP_DIST, ON_FLOOR, BaseFrame, Geometry, geometry, handles, rects_overlap, to_base,
    update_claims, yaw_rotation,
)
from pnp.task.observations import HANDLE_ORDERS, OBS_BLOCKS, OBS_FIELDS, ego_block, observations
from pnp.task.rewards import (
    GRASP_POSES, MAX_OBJ_HEIGHT, collisions, action_rate, default_reward, joint_limit_excess, reward_terms,
)
from pnp.task.state import ACTION_HIGH, ACTION_LOW, ACTION_NAMES, EPISODE_S, HL_DT, PnPState

__all__ = [
    # state, action layout, clock
    "ACTION_HIGH", "ACTION_LOW", "ACTION_NAMES", "EPISODE_S", "HL_DT", "PnPState",
    # geometry
    "FALL_HEIGHT", "FOOTPRINT_HALF", "GRASP_DIST", "ON_FLOOR", "BaseFrame", "Geometry", "geometry", "handles",
    "rects_overlap", "to_base", "update_claims", "yaw_rotation",
    # stage conditions
    "LIFT_HEIGHT", "READY_ALIGN", "READY_XY", "READY_Z", "stage_conditions",
    # reward terms
    "GRASP_POSES", "MAX_OBJ_HEIGHT", "collisions", "action_rate", "default_reward", "joint_limit_excess",
    "reward_terms",
    # observations
    "HANDLE_ORDERS", "OBS_BLOCKS", "OBS_FIELDS", "ego_block", "observations",
]
