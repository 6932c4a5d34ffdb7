"""The one place where stage, condition and reward-term names are listed.

Stage names and the reward table follow the paper (Sec. III-B, Table II). Every
environment backend emits, per robot:

* ``("agents", "reward_terms")``: float ``[..., n_agents, len(REWARD_TERMS)]`` in the
  order of :data:`REWARD_TERMS` (stage-wise terms first, then the fixed terms);
* ``("agents", "stage_conditions")``: bool ``[..., n_agents, len(CONDITIONS)]``, where
  ``CONDITIONS[i]`` is the forward condition of edge ``S_i -> S_{i+1}``.

Curriculum transforms are configured with these names; they know nothing else about
pick-and-place.
"""
from __future__ import annotations

from dataclasses import dataclass

STAGES: tuple[str, ...] = (
    "idle",  # S0
    "gripper_ready",  # S1: gripper aligned above its handle
    "object_grabbed",  # S2
    "object_lifted",  # S3
    "object_on_goal",  # S4: lifted and within the goal radius
    "object_placed",  # S5: back on the floor inside the goal, still held
    "released",  # S6
)

# CONDITIONS[i] is the forward condition of S_i -> S_{i+1}; losing it sends a robot back
# along an allowed backward edge (see pnp.task.stage_graph).
CONDITIONS: tuple[str, ...] = (
    "gripper_ready",
    "object_grabbed",
    "object_lifted",
    "object_on_goal",
    "object_placed",
    "object_released",
)


@dataclass(frozen=True)
class RewardTerm:
    name: str
    stage: int | None  # None: a fixed term (R_fixed), never rescaled
    mu: float  # mu_j of Table II; for fixed terms the constant weight
    low: float  # bounds of the raw term value (used by the Liu et al. schedules)
    high: float


# Table II of the paper, in its order, then R_fixed. Fixed weights are our choice
# (the paper lists the terms but not the weights).
REWARD_TABLE: tuple[RewardTerm, ...] = (
    RewardTerm("gripper_ready_pose", 0, 2.0, 0.0, 1.0),
    RewardTerm("gripper_grasp_pose", 1, 20.0, 0.0, 1.0),
    RewardTerm("object_grabbed", 1, 10.0, 0.0, 1.0),
    RewardTerm("grab_action", 1, 0.2, 0.0, 1.0),
    RewardTerm("object_height", 2, 100.0, 0.0, 0.3),
    RewardTerm("object_to_goal_vel", 3, 50.0, -1.0, 1.0),
    RewardTerm("object_to_goal_dist", 3, 50.0, 0.0, 1.0),
    RewardTerm("object_drop", 4, 100.0, 0.0, 0.3),
    # Table II gates this with (stage >= 5); the env emits it ungated and the curriculum
    # applies the gate because only it knows the stage.
    RewardTerm("grab_action_in_range", 5, 100.0, 0.0, 0.5),
    RewardTerm("object_released_in_goal", 6, 100.0, 0.0, 1.0),
    # The robot's current stage: only the curriculum knows it, so envs emit zeros here.
    RewardTerm("stage_progress", 6, 2.0, 0.0, 6.0),
    RewardTerm("arm_default_pose", 6, 20.0, 0.0, 1.0),
    # R_fixed: penalties, values are >= 0 and the weight is negative.
    RewardTerm("action_rate", None, -0.05, 0.0, float("inf")),
    RewardTerm("collision", None, -1.0, 0.0, 1.0),
    RewardTerm("joint_limits", None, -1.0, 0.0, float("inf")),
    RewardTerm("fall", None, -100.0, 0.0, 1.0),
    # Not in the paper, off unless curriculum.fixed_weights sets it: 1 when the gripper command
    # flips while nothing is held. Closing and opening next to a handle is how the MuJoCo
    # policies knocked boxes over (docs/history/pipeline_single/failures.md).
    RewardTerm("gripper_toggle", None, 0.0, 0.0, 1.0),
    # Not in the paper, off unless set: 1 - cos(tilt) of the box while no robot holds it (0
    # upright, 1 on its side). Fingers tipping the unheld box end most failed MuJoCo trials
    # (docs/history/pipeline_single/run_8.md); a grip lifting one handle tilts it, hence unheld only.
    RewardTerm("object_tilt", None, 0.0, 0.0, 2.0),
    # Not in the paper, off unless set (a positive weight): the base's speed towards its handle
    # (m/s, clamped to [-1, 1]) while the EE is over APPROACH_RADIUS away and nobody holds the box.
    # S0's exp(-3 d) pays ~0 beyond 2 m. A rate of approach sums to the distance covered: walking
    # to and fro earns nothing. Not adopted: an A/B against a stand-still misread as far from the box
    # (docs/history/make_train_cost.md).
    RewardTerm("base_approach", None, 0.0, -1.0, 1.0),
    # Not in the paper, off unless set (a positive weight): 1 with the base within STANCE_M[0] of its
    # handle, 0 beyond STANCE_M[1], linear between, while nobody holds the box. The policies approach
    # every box to ~1.03 m, the arm's full reach, and the mean action stalls where the handle is a
    # little out of it (docs/history/make_train_cost.md, "The stand-still, measured again").
    RewardTerm("base_stance", None, 0.0, 0.0, 1.0),
)

REWARD_TERMS: tuple[str, ...] = tuple(t.name for t in REWARD_TABLE)
STAGE_TERMS: tuple[str, ...] = tuple(t.name for t in REWARD_TABLE if t.stage is not None)
FIXED_TERMS: tuple[str, ...] = tuple(t.name for t in REWARD_TABLE if t.stage is None)
TERM_STAGE: dict[str, int] = {t.name: t.stage for t in REWARD_TABLE if t.stage is not None}
TERM_MU: dict[str, float] = {t.name: t.mu for t in REWARD_TABLE}
STAGE_PROGRESS_TERM = "stage_progress"
# Terms that count only from a given stage on (Table II: "x (stage >= 5)").
STAGE_GATES: dict[str, int] = {"grab_action_in_range": 5}
