"""The schemas of the recipes' own configurations (``recipes/config/<recipe>.yaml``).

Each YAML file holds the values and says why; these dataclasses hold the keys and their
types, so that hydra refuses an unknown key or a wrong type before any work starts. Every
field is required (``MISSING``): the YAML file is the one place its value is declared.
``pnp.training.config.register`` registers them as ``<recipe>_schema``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional

from omegaconf import MISSING


@dataclass
class EvalEnv:
    """The evaluation env's changes to the checkpoint's (null: the checkpoint's, or the paper's)."""

    backend: Optional[str] = MISSING
    num_worlds: int = MISSING
    nthread: Optional[int] = MISSING  # MuJoCo's pool; null: the cores this process may use
    max_episode_steps: Optional[int] = MISSING
    start_range: Optional[List[float]] = MISSING
    box_mass: Optional[List[float]] = None  # the student recipes do not set it
    finger_speed: Optional[float] = None
    kinematic: Any = None  # null, or {option: value}
    low_level: Optional[str] = None
    low_level_checkpoint: Optional[str] = None


@dataclass
class TrialsConfig:
    """What every evaluation of trials reads: a checkpoint, the trials and their seed, where to write."""

    checkpoint: str = MISSING
    runs_root: str = MISSING
    trials: int = MISSING
    seed: Any = MISSING  # an integer, or a protocol name (pnp.training.protocol)
    dirty_reason: Optional[str] = MISSING
    out: Optional[str] = MISSING
    progress: bool = MISSING
    env: EvalEnv = field(default_factory=EvalEnv)


@dataclass
class EvaluateConfig(TrialsConfig):
    phase: Optional[str] = MISSING
    selected: bool = MISSING
    compare: Optional[str] = MISSING
    method: Optional[str] = MISSING
    displacement: Any = MISSING  # null, or {delay_s, distance, clearance}
    noise_scale: Optional[float] = MISSING
    dropout_p: Optional[float] = MISSING
    sample: Optional[List[str]] = MISSING


@dataclass
class EvaluateStudentConfig(TrialsConfig):
    noise_scale: Optional[float] = MISSING
    dropout_p: Optional[float] = MISSING


@dataclass
class Displacement:
    delay_s: float = MISSING
    distance: List[float] = MISSING
    clearance: Optional[float] = MISSING


@dataclass
class Dropout:
    p: float = MISSING
    min_s: float = MISSING
    max_s: float = MISSING
    fields: List[str] = MISSING


@dataclass
class StudentRecoveryConfig(TrialsConfig):
    displacement: Displacement = field(default_factory=Displacement)
    dropout: Dropout = field(default_factory=Dropout)


@dataclass
class SelectCheckpointConfig:
    run: str = MISSING
    candidates: int = MISSING
    seeds: List[int] = MISSING
    trials: int = MISSING
    num_worlds: int = MISSING
    nthread: Optional[int] = MISSING  # MuJoCo's pool; null: the cores this process may use
    progress: bool = MISSING


@dataclass
class VelocityGrid:
    grid_steps: int = MISSING
    repeats: int = MISSING
    settle_s: float = MISSING
    measure_s: float = MISSING


@dataclass
class Pushes:
    episodes: int = MISSING
    seconds: float = MISSING
    interval_s: float = MISSING
    speed: List[float] = MISSING
    payload_kg: List[float] = MISSING


@dataclass
class EETracking:
    worlds: int = MISSING
    switches: int = MISSING
    hold_s: float = MISSING
    delays_s: List[float] = MISSING
    base_commands: List[List[float]] = MISSING


@dataclass
class DualCarry:
    episodes: int = MISSING
    max_steps: int = MISSING
    box_mass_kg: float = MISSING


@dataclass
class LLQualityConfig:
    checkpoint: str = MISSING
    runs_root: str = MISSING
    seed: int = MISSING
    dirty_reason: Optional[str] = MISSING
    out: Optional[str] = MISSING
    nthread: Optional[int] = MISSING  # MuJoCo's pool; null: the cores this process may use
    velocity: VelocityGrid = field(default_factory=VelocityGrid)
    pushes: Pushes = field(default_factory=Pushes)
    ee: EETracking = field(default_factory=EETracking)
    carry: DualCarry = field(default_factory=DualCarry)


@dataclass
class Table1Eval:
    trials: int = MISSING
    backend: str = MISSING
    num_worlds: int = MISSING
    seed: int = MISSING
    nthread: Optional[int] = MISSING  # MuJoCo's pool; null: the cores this process may use
    start_range: Optional[List[float]] = MISSING
    max_episode_steps: Optional[int] = MISSING


@dataclass
class Table1Tuning:
    seed: int = MISSING  # the candidates' training seed: none of the reported seeds
    candidates: Dict[str, Any] = MISSING  # name -> {phase: {override key: value}}; as_built first
    eval: Table1Eval = field(default_factory=Table1Eval)  # selection trials


@dataclass
class Table1Config:
    methods: List[str] = MISSING
    ours: str = MISSING
    seeds: List[int] = MISSING
    runs_dir: str = MISSING
    records_dir: str = MISSING
    out: str = MISSING
    thresholds: Dict[str, float] = MISSING
    window: int = MISSING
    curve_bins: int = MISSING
    mujoco_seeds: List[int] = MISSING
    eval_kinematic: Table1Eval = field(default_factory=Table1Eval)
    eval: Table1Eval = field(default_factory=Table1Eval)
    tuning: Table1Tuning = field(default_factory=Table1Tuning)
    train: List[str] = MISSING


@dataclass
class AblationEEConfig:
    schedules: List[str] = MISSING
    variants: Dict[str, Any] = MISSING
    seeds: List[int] = MISSING
    iterations: int = MISSING
    eval_trials: int = MISSING
    eval_seed: int = MISSING
    runs_dir: str = MISSING
    records_dir: str = MISSING
    out: str = MISSING
    window: int = MISSING
    train: List[str] = MISSING


@dataclass
class SeedGoals:
    mean_success: float = MISSING
    worst_success: float = MISSING
    max_train_wall_s: float = MISSING
    max_mujoco_frames: int = MISSING


@dataclass
class SeedStudyConfig:
    runs: List[str] = MISSING
    eval_name: str = MISSING
    title: str = MISSING
    out: str = MISSING
    dirty_reason: Optional[str] = MISSING
    goals: SeedGoals = field(default_factory=SeedGoals)


RECIPE_SCHEMAS = {"evaluate": EvaluateConfig, "evaluate_student": EvaluateStudentConfig,
                  "student_recovery": StudentRecoveryConfig, "select_checkpoint": SelectCheckpointConfig,
                  "ll_quality": LLQualityConfig, "table1": Table1Config, "ablation_ee": AblationEEConfig,
                  "seed_study": SeedStudyConfig}
