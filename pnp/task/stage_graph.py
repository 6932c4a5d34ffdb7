"""Pick-and-place's stage graph (paper Fig. 3) and reward configuration (Table II); the
graph class itself is task-free, in ``pnp.transforms`` (:class:`StageGraph`)."""
from __future__ import annotations

from pnp.task.terms import (
    CONDITIONS,
    FIXED_TERMS,
    REWARD_TABLE,
    REWARD_TERMS,
    STAGE_GATES,
    STAGE_PROGRESS_TERM,
    STAGES,
    TERM_STAGE,
)
from pnp.transforms import StageGraph

# Our reading of the paper's figure: back from "gripper ready"/"grabbed" to idle when the
# gripper leaves the handle, and back around release when the box is lifted again.
PNP_BACKWARD_EDGES: tuple[tuple[str, str], ...] = (
    ("gripper_ready", "idle"),
    ("object_grabbed", "idle"),
    ("object_placed", "object_on_goal"),
    ("released", "object_placed"),
)

__all__ = ["PNP_BACKWARD_EDGES", "StageGraph", "pnp_default_reward_config", "pnp_default_stage_graph"]


def pnp_default_stage_graph() -> StageGraph:
    """The paper's 7-stage pick-and-place graph with our reading of its backward edges."""
    return StageGraph(STAGES, CONDITIONS, PNP_BACKWARD_EDGES)


def pnp_default_reward_config() -> dict:
    """Keyword arguments of ``pnp.transforms.make_reward_schedule`` for Table II.

    Add ``K`` and ``mu_min`` for the dynamic schedule.
    """
    return dict(
        term_names=REWARD_TERMS,
        term_stage=dict(TERM_STAGE),
        mu={t.name: t.mu for t in REWARD_TABLE if t.stage is not None},
        fixed_weights={t.name: t.mu for t in REWARD_TABLE if t.name in FIXED_TERMS},
        low={t.name: t.low for t in REWARD_TABLE if t.stage is not None},
        high={t.name: t.high for t in REWARD_TABLE if t.stage is not None},
        n_stages=len(STAGES),
        stage_progress_term=STAGE_PROGRESS_TERM,
        stage_gates=dict(STAGE_GATES),
    )
