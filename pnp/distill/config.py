"""The distillation configuration, declared once: dataclasses hydra validates
``recipes/config/distill.yaml``, its experiments and every override against (unknown keys
are refused). The env, reward, model, loss, optimiser, collection and logger sections are
the teacher's own dataclasses (``pnp.training.config``).

Noise model (``noise.sigma``, per observation field, in the observation's units; each
column gets independent N(0, sigma^2) noise every 0.1 s step). Spatial fields are in the
robot's base frame, so their error is the mocap error of box and base together:

* ego: ``base_vel`` 0.1 (m/s, rad/s: a state estimator's, as legged_gym's 0.1 m/s);
  ``arm_q`` 0.01 rad (legged_gym's joint-position noise; encoders are finer, this covers
  calibration and backlash); ``arm_qd`` 0.05 (the observation is 0.1 qd: 0.5 rad/s);
  ``ee_pos`` 0.01 m and ``ee_yaw_sincos`` 0.01 (forward kinematics of noisy joints over a
  ~1 m reach; the student does not see them, the noisy teacher does); ``gripper_opening``
  0.02 (of the 140 mm stroke: 3 mm). ``pad_touch`` (binary contacts) and ``last_action``
  (the policy's own output) stay exact.
* goal: 0.02 m (the base pose from mocap: ~1 cm, and 0.5 deg of yaw at 2 m).
* object (mocap): positions, ``handles`` and ``handles_from_ee`` 0.02 m; axes 0.02
  (~1 deg); ``box_lin_vel`` 0.05 m/s and ``box_ang_vel`` 0.1 rad/s (differentiated
  mocap, filtered); ``box_size`` 0.01 m.
* neighbour (the other robot's state, base from mocap): 0.02 everywhere but ``pad_touch``.

Dropouts (``noise.dropout``): the object's mocap fields freeze together at the last value
seen for U[0.2, 2] s; one starts after a seen step with probability 0.01 (about one per
10 s episode at 10 Hz), as the paper reports mocap dropouts on hardware.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from typing import Dict, List, Optional

from hydra.core.config_store import ConfigStore
from omegaconf import DictConfig, OmegaConf

from pnp.training.config import CurriculumConfig, RunConfig
from pnp.training.migration import drop_retired

MOCAP_FIELDS = ["object.box_pos", "object.box_x_axis", "object.box_y_axis", "object.box_lin_vel",
                "object.box_ang_vel", "object.handles"]


def _sigma() -> Dict[str, Dict[str, float]]:
    mocap = 0.02
    return {
        "ego": {"base_vel": 0.1, "arm_q": 0.01, "arm_qd": 0.05, "ee_pos": 0.01, "ee_yaw_sincos": 0.01,
                "gripper_opening": 0.02},
        "goal": {"goal_xy": mocap, "goal_dist": mocap},
        "object": {"box_pos": mocap, "box_x_axis": mocap, "box_y_axis": mocap, "box_lin_vel": 0.05,
                   "box_ang_vel": 0.1, "handles": mocap, "handles_from_ee": mocap, "box_size": 0.01},
        "neighbour": {"base_xy": mocap, "yaw_sincos": mocap, "ee_pos": mocap, "gripper_opening": mocap},
    }



Direction = StrEnum("Direction", ["forward", "reverse"])

@dataclass
class DropoutConfig:
    """Fields (``block.field``, contiguous columns) that freeze together at their last
    seen value for U[min_s, max_s] seconds; a dropout starts after a seen step with
    probability ``p``."""

    fields: List[str] = field(default_factory=lambda: list(MOCAP_FIELDS))
    p: float = 0.01
    min_s: float = 0.2
    max_s: float = 2.0


@dataclass
class NoiseConfig:
    """The observation noise of the student (and of the noisy teacher in evaluation)."""

    # block -> field -> std (pnp.task.observations.OBS_FIELDS); fields not listed stay exact
    sigma: Dict[str, Dict[str, float]] = field(default_factory=_sigma)
    scale: float = 1.0  # multiplies every sigma (0: no Gaussian noise; dropouts still apply)
    dropout: DropoutConfig = field(default_factory=DropoutConfig)


@dataclass
class StudentConfig:
    """The student's observation: the noisy one without ``drop_fields``, followed by the last
    ``history_length`` values of ``history_field``, most recent first.

    Five 0.1 s steps (0.5 s): the EE pose is a function of the arm joints, and the history
    averages their noise (0.01 rad / sqrt(5)) and shows where the arm is heading while
    the low level tracks the last EE command, which settles within a few steps. ``arm_q``
    itself is dropped: the history's first entry is its current value. ``handles_from_ee``
    goes too: with ``handles`` it would give the EE position away.
    """

    history_field: str = "ego.arm_q"
    history_length: int = 5
    drop_fields: List[str] = field(
        default_factory=lambda: ["ego.arm_q", "ego.ee_pos", "ego.ee_yaw_sincos", "object.handles_from_ee"])
    # A diagnostic, not the paper's student: the stage one-hot as a second input (how much of
    # a student's gap to its teacher the stage it cannot see is).
    sees_stage: bool = False
    # > 0: a GRU of this many cells over the episode's observations, its state read by the MLP
    # beside them (pnp.training.recurrent: the stage is latched, a function of the episode so
    # far); both quoted students use 128. 0: an MLP over the observation now.
    recurrent_cells: int = 128
    # > 0 (needs recurrent_cells): the GRU state also predicts the env's stage, a cross-entropy
    # of this weight in training; the deployed student reads no stage, as the critic's inputs.
    stage_loss_coeff: float = 0.0


@dataclass
class KLConfig:
    """The teacher and the KL term of ``pnp.losses.DistillationPPOLoss``."""

    teacher: Optional[str] = None  # the teacher's checkpoint (file or run folder), frozen
    beta: float = 1.0
    direction: Direction = Direction.forward  # forward: KL(teacher || student) | reverse: KL(student || teacher)
    # null: beta stays; else beta moves linearly to beta_final over anneal_iterations
    beta_final: Optional[float] = None
    anneal_iterations: int = 0
    # The critic starts as the teacher's (same clean observation and stage as input): its
    # values are those of a good policy from the first iteration.
    critic_from_teacher: bool = True
    # True: curriculum.backward_edges may add edges to the teacher's graph, and the teacher
    # labels with this graph's stage. Why: where the teacher's graph has no way back (dual: S3),
    # a dropped box stays S3 for the teacher and looks like S0 to the student; 78 % of the dual
    # student's S3 steps had no grasp, each labelled with the teacher's S3 action (docs/history/distillation.md).
    add_backward_edges: bool = False


@dataclass
class DistillConfig(RunConfig):
    total_iterations: int = 1000
    distill: KLConfig = field(default_factory=KLConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    student: StudentConfig = field(default_factory=StudentConfig)
    # The student's reward: the stage-wise terms at their mu_j, no curriculum (paper Sec. III-C).
    curriculum: CurriculumConfig = field(default_factory=lambda: CurriculumConfig(schedule="fixed"))


def distill_config(saved: dict) -> DictConfig:
    """A student checkpoint's stored configuration, validated against the schema."""
    if "distill" not in saved:
        raise ValueError("not a student checkpoint (its configuration has no 'distill' section): "
                         "a teacher's is evaluated with recipes/evaluate.py")
    return OmegaConf.merge(OmegaConf.structured(DistillConfig), drop_retired(saved))


def register() -> None:
    """Register the schema with hydra's ConfigStore as ``distill_schema`` (distill.yaml's base)."""
    ConfigStore.instance().store(name="distill_schema", node=DistillConfig)
