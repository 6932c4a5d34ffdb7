"""The training configuration, declared once: dataclasses that hydra validates every YAML
file and command-line override against (``recipes/config/``), and that old checkpoints'
configurations are migrated into (``pnp.training.migration``).

Defaults live here and nowhere else: code reads ``cfg.<group>.<key>`` without fallbacks.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional

from hydra.core.config_store import ConfigStore

from pnp.sim.layout import START_RANGE
from pnp.training.choices import (
    Backend, EpisodeStage, GraspDist, GraspPose, HandleOrder, LoggerBackend, LowLevel, LrSchedule, ValueNorm,
)
from pnp.legs.locomotion import ACTION_SCALE, TRACKING_SIGMA
from pnp.sim.robot import LEG_KD, LEG_KP
from pnp.task import ACTION_HIGH, ACTION_LOW, GRASP_DIST
from pnp.task.ee_tracking import POINT_RING, TRACK_SIGMA


@dataclass
class KinematicOptions:
    """Options of the kinematic backend only; a MuJoCo env refuses them (real contacts)."""

    box_blocks_base: bool = False  # a base does not step into a box it does not hold
    grasp_holds: bool = False  # two robots: a closed gripper keeps its bar, its EE follows the grasp point
    grasp_dist: float = GRASP_DIST  # m, EE to bar within which closing fingers grasp (and keep it)


@dataclass
class LocomotionConfig:
    """``env.task=locomotion``, the learned low level's leg policy (envs/locomotion_env.py):
    legged_gym's ANYmal C flat task where it has a number, else ours."""

    # vx, vy (m/s), yaw rate (rad/s): the HL policy's base-velocity bounds (pnp.task ACTION_LOW/HIGH).
    command_low: List[float] = field(default_factory=lambda: list(ACTION_LOW[:3]))
    command_high: List[float] = field(default_factory=lambda: list(ACTION_HIGH[:3]))
    command_resample_s: float = 4.0  # legged_gym
    # Ours: this share of resampled commands is zero; the HL policy stands still to grasp.
    stand_share: float = 0.1
    arm_resample_s: float = 2.0  # ours: a new random EE goal in the HL action's box this often
    payload_mass: List[float] = field(default_factory=lambda: [0.0, 2.5])  # kg on the gripper (boxes 1.0-2.2)
    push_interval_s: float = 15.0  # legged_gym; the first push of an episode at a random time
    push_speed: List[float] = field(default_factory=lambda: [0.5, 1.0])  # m/s horizontal kick (legged_gym: up to 1)
    # Ours: only the feet touch the floor, so a fall is read off the trunk (stands at ~0.63 m).
    fall_height: float = 0.35  # m, trunk centre
    fall_tilt: float = 1.0  # rad between the trunk's z axis and the vertical
    # legged_gym's only_positive_rewards (True there): each step's summed reward clipped at 0,
    # so the penalties cannot outweigh what a gait being learned earns. Off in our first leg
    # policy (docs/history/low_level.md).
    only_positive_rewards: bool = False
    # The leg servos and the action's scale (pnp.legs.locomotion.LegServo); the defaults are
    # robot.py's model (legged_gym's ANYmal C kp 80, kd 2) and legged_gym's 0.5 rad. The leg
    # policy's checkpoint carries them to the legged backend (docs/history/low_level.md: kp 80 sags).
    leg_kp: float = LEG_KP
    leg_kd: float = LEG_KD
    action_scale: float = ACTION_SCALE
    # (m/s)^2 and (rad/s)^2: the tracking kernel exp(-err^2 / sigma); legged_gym's 0.25 pays
    # 92 % of the reward at a 0.14 m/s error.
    tracking_sigma: float = TRACKING_SIGMA


@dataclass
class EETrackingConfig:
    """The 4-point EE-tracking ablation's task (env.task=ee_tracking only; pnp.task.ee_tracking)."""

    track_rule: str = "gated"  # plain | saturated | gated: how point k's term depends on the points touched
    track_sigma: List[float] = field(default_factory=lambda: list(TRACK_SIGMA))  # m, the coarse and fine kernels
    point_ring: List[float] = field(default_factory=lambda: list(POINT_RING))  # m, points' distance from the start


@dataclass
class EnvConfig:
    task: str = "pnp"  # pnp | ee_tracking (the 4-point ablation, one robot) | locomotion (the leg policy)
    backend: Backend = Backend.mujoco
    num_worlds: int = 64
    num_robots: int = 1
    kinematic: KinematicOptions = field(default_factory=KinematicOptions)  # all off on MuJoCo
    boxes: Optional[str] = None  # null: the robot count's boxes (paper); single | dual: those assets
    nthread: Optional[int] = None  # MuJoCo's pool; null: the cores this process may use
    max_episode_steps: Optional[int] = None  # null: the task env's own (pick-and-place: the paper's 45 s, 450 steps)
    start_range: List[float] = field(default_factory=lambda: list(START_RANGE))  # m, robots and box from the goal
    # S6 terms pay for staying released (envs/pnp_env.py); evaluation terminates at success.
    terminate_on_success: bool = False
    handle_order: HandleOrder = HandleOrder.identity  # ours (pnp.task)
    handle_claim: bool = False  # each robot keeps the handle it was given at the episode start (ours)
    # Evaluation sets it: trial i's layout depends on (seed, i) only (docs/guide/evaluation.md).
    paired_trials: bool = False
    # [lo, hi] kg: every box's mass drawn uniformly (e.g. the paper's 2.0 kg hardware box); null: the assets'.
    box_mass: Optional[List[float]] = None
    # Ours (pick-and-place): {action name: [lo, hi]} narrowing the paper's action box (pnp.task
    # ACTION_LOW/HIGH), e.g. {ee_x: [0.3, 0.85], ee_y: [-0.45, 0.45]}: the EE commands the arm reaches
    # at a handle's height, so that a handle out of reach is reached by walking. Empty: the paper's.
    # On the command line: +env.action_bounds.ee_x=[0.3,0.85]
    action_bounds: Dict[str, List[float]] = field(default_factory=dict)
    # What Table II's gripper_grasp_pose pays (pick-and-place): height, the EE at its handle's height
    # (our reading); bar (ours), the EE at the handle bar: exp(-10 x distance to the bar), so the
    # last centimetres across the bar pay too (pnp.task.rewards.GRASP_POSES).
    grasp_pose: GraspPose = GraspPose.height
    locomotion: LocomotionConfig = field(default_factory=LocomotionConfig)  # env.task=locomotion only
    ee_tracking: EETrackingConfig = field(default_factory=EETrackingConfig)  # env.task=ee_tracking only
    # ideal: planar base, IK arm (pnp.sim.executor). learned: legs walked by a locomotion policy
    # (pnp.legs.backend; MuJoCo only) from low_level_checkpoint, a task=locomotion run.
    low_level: LowLevel = LowLevel.ideal
    low_level_checkpoint: Optional[str] = None
    # MuJoCo only, m/s per finger: finger targets ramp at this speed. null: they jump, and
    # the servos drive the pads through a handle bar in one substep (docs/history/pipeline_single.md).
    finger_speed: Optional[float] = None


@dataclass
class CurriculumConfig:
    schedule: str = "dynamic"  # dynamic | liu_max | liu_min | fixed
    # rho_j climbs from mu_min = 0.1 to the largest mu_j = 100 in 4 episodes whose lambda is
    # its stage (the paper says only K > 1); with K = 2 the S2 terms took ~100 iterations to
    # reach mu, with K = 8 ~40.
    K: float = 8.0
    mu_min: float = 0.1  # <= min mu_j = 0.2 (grab action), as Eq. 2 requires
    final_after: int = 5
    # Not in the paper (0 = Eq. 2): terms of stages below lambda keep rho_j >= this share of
    # mu_j. Eq. 2 divides the ready-pose rho by K per episode that peaks in S1.
    completed_floor: float = 0.0
    # Ours: a run starts every slot in the paper's final stage (scales fixed at mu_j). For a
    # phase that moves a policy which reaches S6 onto new worlds: 30 s kinematic episodes left
    # 24 % of kin_far's slots final, and MuJoCo under live scales did not learn (the hand-run
    # chain and the dual pipeline, which did, handed over 100 % and 95 % final slots).
    start_final: bool = False
    # lambda(e) of Eq. 2: peak (highest stage of the episode) | final (stage it ends in).
    # Under final, grasp-drop-regrasp episodes ended in S0-S2 by chance and the S2 terms
    # stayed at mu_min for 1600 iterations; under peak lifting followed within 30.
    episode_stage: EpisodeStage = EpisodeStage.peak
    # null: the task's backward edges; else [from, to] stage names, e.g. without
    # placed -> on_goal (MuJoCo's grasp flickers with the box on the floor).
    backward_edges: Optional[List[Any]] = None
    # Ours, beside Table II's (grab action in range, stage >= 5): stage-wise terms that count
    # only from a stage on, {term: stage index}. Under fixed scales on MuJoCo the legs pushed
    # the box to the goal for the S3 terms, which Table II pays at any stage: the paper's
    # "kicking the object to the destination" (docs/history/pipeline_single.md, run 6).
    stage_gates: Dict[str, int] = field(default_factory=dict)
    stage_rewards: bool = True  # false: control run with R_fixed only (stage terms weighted 0)
    fixed_weights: Dict[str, float] = field(default_factory=dict)  # R_fixed weights by term name


@dataclass
class ModelConfig:
    actor_cells: List[int] = field(default_factory=lambda: [256, 256])
    critic_cells: List[int] = field(default_factory=lambda: [256, 256])
    init_scale: float = 1.0  # policy std (pre-tanh) at initialisation
    grasp_dist: GraspDist = GraspDist.bernoulli  # bernoulli (losses/distributions.py) | tanh_normal (a probability)
    min_scale: float = 0.0  # > 0: floor on every continuous entry's pre-tanh std
    # > 0: floor on the grasp entry's pre-tanh std, tanh_normal gripper only (the Bernoulli's
    # ignores its scale); the single-robot chain began with it (docs/history/train_single/LINEAGE.md).
    grasp_min_scale: float = 0.0
    # > 0, Bernoulli gripper only: a soft floor on its closing probability, so that grasps are
    # still tried where p would collapse to ~0 (models.GripperFloor).
    grasp_min_prob: float = 0.0
    # > 0: a loss term, this times the mean squared distance of the gripper logit below the
    # floor (models.GripperFloor.penalty), so that the floor's gradient does not vanish.
    grasp_floor_coeff: float = 0.0
    # > 0 (needs grasp_min_prob): in the stages listed below, a soft ceiling on the closing
    # probability at 1 - this, so that a held box is let go now and then where letting go is
    # the task. Held boxes drove the logit to ~8 (p ~ 0.9998) and placed boxes sat for
    # hundreds of iterations without a release (docs/history/pipeline_single.md, run 3).
    grasp_open_min_prob: float = 0.0
    grasp_open_stages: List[int] = field(default_factory=lambda: [5, 6])  # pick-and-place: S5 placed, S6 released
    max_scale: Optional[float] = None  # ceiling on the continuous entries' pre-tanh std
    obs_norm: bool = True  # running observation normalisation (in the checkpoint)
    # none: one actor and one critic (ours). The per-stage baselines (pnp.baselines.per_stage)
    # keep one actor and one critic per stage: bendikas, the sub-task's pair acts in every
    # stage (Bendikas et al.); erskine, each stage's actor acts, every stage's critic values
    # (Erskine et al.). Their reward is curriculum.schedule=fixed.
    per_stage: str = "none"


@dataclass
class LossConfig:
    clip_epsilon: float = 0.2
    entropy_coeff: float = 0.005
    critic_coeff: float = 1.0
    loss_critic_type: str = "l2"
    gamma: float = 0.99
    lmbda: float = 0.95
    value_norm: ValueNorm = ValueNorm.popart
    popart_beta: float = 0.98  # per-iteration EMA of the return statistics (~50 iterations)


@dataclass
class OptimConfig:
    lr: float = 1.0e-3  # initial lr when adaptive
    lr_schedule: LrSchedule = LrSchedule.adaptive  # adaptive: KL-driven, as rsl_rl
    desired_kl: float = 0.01
    min_lr: float = 1.0e-5
    max_lr: float = 1.0e-2
    max_grad_norm: float = 1.0


@dataclass
class CollectConfig:
    frames_per_batch: int = 2048  # worlds x steps per iteration
    num_epochs: int = 5
    minibatch_size: int = 512
    # Not in the paper: this share of episodes first takes the policy's mean action for
    # 1..roll_in_max_steps steps, then samples (pnp.training.collect.MeanRollIn).
    roll_in_share: float = 0.0
    roll_in_max_steps: int = 200
    # Start every world's first episode at a random step of env.max_episode_steps.
    desync_episodes: bool = False


@dataclass
class SequentialConfig:
    """Bendikas et al.: sub-task k (episodes end with success at S_{k+1}) trains until its
    success rate over the last ``window`` iterations, weighted by episodes, reaches
    ``min_success``, or until it has used ``max_frames``; then policy k+1 starts from policy k."""

    min_success: float = 0.9
    window: int = 20
    max_frames: int = 2_000_000
    # Reaching S_{k+1} pays this share of the sub-task's best return, sum_j mu_j high_j /
    # (1 - loss.gamma) over its terms. Why: the stage terms are positive, so without it an
    # episode that ends at success earns less than one that hovers just short of it.
    success_bonus: float = 1.0


@dataclass
class CooperativeConfig:
    """Erskine et al.: policy i maximises ``(1 - mix) A_i + mix A_{i+1}``."""

    mix: float = 0.5
    # Critic i's reward in stages above i: this share of stage i's best step, sum_j mu_j high_j
    # over its terms (pnp.transforms.baselines.StageRewards); 0: nothing once stage i is left.
    completed_share: float = 0.0


@dataclass
class BaselineConfig:
    """Settings of the per-stage baselines, read when ``model.per_stage`` names one."""

    bendikas: SequentialConfig = field(default_factory=SequentialConfig)
    erskine: CooperativeConfig = field(default_factory=CooperativeConfig)


@dataclass
class LoggerConfig:
    backend: LoggerBackend = LoggerBackend.wandb
    project: str = "pnp-curriculum"
    exp_name: Optional[str] = None  # null: <backend>_<robots>r_<schedule>_s<seed>
    offline: bool = True


@dataclass
class ExitRule:
    """A phase ends early once ``metric`` (a metrics.jsonl column), averaged over the last
    ``window`` iterations weighted by their episode counts, reaches ``min`` (exit "rule"), or,
    with ``plateau``, once that mean has not risen ``min_delta`` above its best of the phase
    for ``plateau`` iterations (exit "plateau": more of the same batch and noise buys nothing)."""

    metric: str = "success_rate"
    min: float = 0.9
    window: int = 50
    plateau: Optional[int] = None
    min_delta: float = 0.02


@dataclass
class PhaseConfig:
    """One phase of a pipeline: overrides of this configuration (dotted keys), an exit
    rule measured in training, and a frame budget that ends it regardless."""

    overrides: Dict[str, Any] = field(default_factory=dict)
    # Another phase's name: its overrides first, this phase's on top (a key set here replaces
    # the other's value); the exit rule and budget stay this phase's own.
    extends: Optional[str] = None
    exit: Optional[ExitRule] = None
    max_frames: int = 10_000_000
    # Instead of max_frames: the phase ends once the pipeline's frames (earlier phases' and
    # its own) reach this, so it gets what an earlier phase ended by its rule left unused
    # (a comparison's equal budget per run).
    until_total_frames: Optional[int] = None


@dataclass
class ThreadsConfig:
    """torch's intra-op threads, which the trainer sets and prints rather than leave to torch
    (one per core, which cost 5-7x beside one other process: issue 64). null: the cores this
    process may use. MuJoCo's pool is ``env.nthread``."""

    # Measured: docs/history/make_train_cost.md (beside another process, update=1).
    collect: Optional[int] = 1  # the policy's forward (the env steps on one thread itself)
    update: Optional[int] = None  # the PPO update: ~1.5 s on 2 cores alone against ~2.5 s on one


@dataclass
class RunConfig:
    """What every on-policy run has (training and distillation): its length, checkpoints,
    folder and the env, reward, model, loss, optimiser, collection and logger sections."""

    seed: int = 0
    total_iterations: int = 3000
    max_wall_hours: Optional[float] = None  # stop (with a checkpoint) after this much wall time
    checkpoint_every_min: float = 5.0
    # Also keep a copy of the checkpoint every this many iterations, snapshots/iteration_<n>.pt:
    # the candidates recipes/select_checkpoint.py compares on seeds other than the reporting one. 0: none.
    snapshot_every: int = 0
    out_dir: Optional[str] = None  # null: the hydra run folder; a pipeline or distillation resumes one with a checkpoint
    runs_root: str = "runs"
    progress: bool = True
    # A checkpoint that starts this run: a teacher's actor, critic and Adam state; a student's actor
    # (pnp.distill: a student moved to a new teacher or env, e.g. the legs; the critic as critic_from_teacher says).
    warm_start: Optional[str] = None
    env: EnvConfig = field(default_factory=EnvConfig)
    curriculum: CurriculumConfig = field(default_factory=CurriculumConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    collect: CollectConfig = field(default_factory=CollectConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    threads: ThreadsConfig = field(default_factory=ThreadsConfig)
    # Where the networks, the loss and the PPO update run: cpu | cuda | cuda:<index>. The envs
    # stay on the CPU; each step's tensordict crosses over (pnp.training.device).
    device: str = "cpu"


@dataclass
class TrainConfig(RunConfig):
    resume: Any = False  # true/latest: newest runs/**/checkpoint.pt; or a run folder / file
    # Also its curriculum state. Not for a new task: a slot in the final stage keeps rho = mu.
    warm_start_curriculum: bool = False
    warm_start_fold_constant: bool = False  # blind the nets to inputs that never moved in the source run
    baseline: BaselineConfig = field(default_factory=BaselineConfig)
    # Phases by name, declared once: an experiment that extends another reuses its phases.
    phases: Dict[str, PhaseConfig] = field(default_factory=dict)
    # Non-empty: run these phases (names in ``phases``) back to back in out_dir, each
    # warm-started from the last (pnp.training.pipeline); rerunning resumes where it stopped.
    pipeline: List[str] = field(default_factory=list)
    # A run folder whose finished phases this pipeline declares alike (names and overrides, from
    # the first on): a new out_dir starts after them, from their checkpoints there (an A/B of a later phase).
    branch_from: Optional[str] = None


def register() -> None:
    """Register the schemas with hydra's ConfigStore: ``train_schema`` (train.yaml's base) and
    each recipe's ``<recipe>_schema`` (``pnp.training.recipe_configs``)."""
    from pnp.training.recipe_configs import RECIPE_SCHEMAS

    store = ConfigStore.instance()
    store.store(name="train_schema", node=TrainConfig)
    for name, schema in RECIPE_SCHEMAS.items():
        store.store(name=f"{name}_schema", node=schema)
