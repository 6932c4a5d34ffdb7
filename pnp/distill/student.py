"""The student of teacher-student distillation (paper Sec. III-C): its observation, its
networks, and the frozen teacher that labels the states it visits.

The env carries two views of every state: the clean observation and stage one-hot, which
the teacher and the critic read, and the student's observation (``STUDENT_OBS``): the
clean one with per-field noise and mocap dropouts (``ObservationNoise``), without its EE
pose, followed by a history of its noisy arm joints (``ColumnHistory``); no stage (a
recurrent student carries a GRU state over the episode instead, ``pnp.training.recurrent``). The
reward stays the env's stage-wise reward (at fixed mu_j for the student).
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torchrl.envs import Transform, TransformedEnv
from torchrl.modules import ProbabilisticActor

from pnp.task import HL_DT
from pnp.task.observations import OBS_BLOCKS, OBS_FIELDS
from pnp.training.checkpoint import load_checkpoint, resolve_checkpoint, seed_everything
from pnp.training.migration import migrate
from pnp.distill.config import NoiseConfig, distill_config
from pnp.training.keys import ACTION, LOC, LOG_PROB, OBS, SCALE, STAGE_ONE_HOT, STUDENT_OBS, TEACHER_LOC, TEACHER_SCALE
from pnp.training.models import AgentNet, ObsNorm, PopArt, fold_constant_inputs, make_models
from pnp.training.recurrent import HIDDEN, HIDDEN_NEXT, STEP_COUNT, RecurrentStudentNet
from pnp.training.rollout import evaluation_env_config, run_trials, trained_models
from pnp.training.tasks import make_env, stage_graph
from pnp.transforms import ColumnHistory, ObservationNoise


def _field_columns() -> dict[str, tuple[int, int]]:
    out, offset = {}, 0
    for block, width in OBS_BLOCKS.items():  # the env concatenates the blocks in this order
        for name, cols in OBS_FIELDS[block].items():
            out[f"{block}.{name}"] = (offset + cols.start, offset + cols.stop)
        offset += width
    return out


# "block.field" -> its [start, stop) columns in ("agents", "observation")
FIELD_COLUMNS = _field_columns()
# What the policy sees: the student's noisy observation, the teacher's with the same noise, or clean.
VIEWS = ("student", "noisy", "clean")
# The evaluation's three runs: (policy, view).
EVALUATIONS = {"student": "student", "teacher_noisy": "noisy", "teacher_clean": "clean"}


def field_columns(name: str, where: str) -> tuple[int, int]:
    if name not in FIELD_COLUMNS:
        raise ValueError(f"{where}: unknown observation field {name!r}; fields are {sorted(FIELD_COLUMNS)}")
    return FIELD_COLUMNS[name]


def noise_transforms(noise: DictConfig, in_key, out_key, seed: int, num_robots: int) -> list[ObservationNoise]:
    """Gaussian noise per field (``noise.sigma``), then the dropouts of ``noise.dropout``.

    Two transforms: the dropout fields freeze together (one mocap stream), while their
    noise differs per field; the second holds the first one's noisy output. A robot alone
    has no neighbour: that block stays the zeros it is (noise there would be pure noise
    inputs, at unit scale after normalisation).
    """
    if not float(noise.scale) >= 0.0:
        raise ValueError(f"noise.scale={noise.scale!r}: must be >= 0")
    fields = {}
    for block, sigmas in noise.sigma.items():
        if block == "neighbour" and num_robots == 1:
            continue
        for name, std in sigmas.items():
            full = f"{block}.{name}"
            fields[full] = (field_columns(full, "noise.sigma"), float(std) * float(noise.scale))
    out = [ObservationNoise(fields, in_key=in_key, out_key=out_key, dt=HL_DT, generator_seed=seed)]
    drop = noise.dropout
    if drop.fields and drop.p > 0:
        spans = sorted(field_columns(n, "noise.dropout.fields") for n in drop.fields)
        gaps = [(a, b) for a, b in itertools.pairwise(spans) if b[0] != a[1]]
        if gaps:
            raise ValueError(f"noise.dropout.fields {list(drop.fields)} must be adjacent columns (one mocap "
                             f"stream), columns {list(gaps[0][0])} and {list(gaps[0][1])} are not")
        mocap = {"mocap": ((spans[0][0], spans[-1][1]), 0.0)}
        out.append(ObservationNoise(mocap, in_key=out_key, dropouts={"mocap": (float(drop.p), float(drop.min_s),
                                    float(drop.max_s))}, dt=HL_DT, generator_seed=seed + 1))
    return out


def history_transform(student: DictConfig) -> ColumnHistory:
    """The EE pose fields replaced by a history of arm joints, in ``STUDENT_OBS``."""
    drop = [field_columns(n, "student.drop_fields") for n in student.drop_fields]
    return ColumnHistory(field_columns(student.history_field, "student.history_field"), int(student.history_length),
                         in_key=STUDENT_OBS, drop=drop)


def observation_transforms(cfg: DictConfig, view: str, seed: int) -> list[Transform]:
    robots = int(cfg.env.num_robots)
    if view == "student":  # the clean observation stays for the teacher and the critic
        return [*noise_transforms(cfg.noise, OBS, STUDENT_OBS, seed, robots), history_transform(cfg.student)]
    if view == "noisy":  # the teacher's own layout, with the student's noise, in place
        return noise_transforms(cfg.noise, OBS, OBS, seed, robots)
    if view == "clean":
        return []
    raise ValueError(f"view must be one of {VIEWS}, got {view!r}")


def add_observation_noise(env: TransformedEnv, seed: int, scale: float | None = None,
                          dropout_p: float | None = None, dropout_s: tuple[float, float] | None = None) -> dict:
    """The student's noise model (the schema's, with ``scale``, ``dropout_p`` and the dropout
    durations ``dropout_s`` (min, max) replaced where given) on ``env``'s own observation, in
    place, before its reward schedule: a teacher evaluated under the student's conditions.
    Returns the noise model used."""
    noise = OmegaConf.structured(NoiseConfig)
    if scale is not None:
        noise.scale = float(scale)
    if dropout_p is not None:
        noise.dropout.p = float(dropout_p)
    if dropout_s is not None:
        noise.dropout.min_s, noise.dropout.max_s = (float(x) for x in dropout_s)
    for t in noise_transforms(noise, OBS, OBS, seed, int(env.base_env.num_robots)):
        env.insert_transform(len(env.transform) - 1, t)
    return OmegaConf.to_container(noise)


def make_student_env(cfg: DictConfig, seed: int, view: str = "student") -> TransformedEnv:
    """``make_env``'s env with the observation transforms of ``view``, inserted before the
    reward schedule so that ``schedule_of`` still finds it last."""
    env = make_env(cfg.env, cfg.curriculum, seed)
    for t in observation_transforms(cfg, view, seed):
        env.insert_transform(len(env.transform) - 1, t)
    return env


class StudentNet(AgentNet):
    """:class:`AgentNet` over the student's observation alone (no stage input), or with the
    stage where ``student.sees_stage`` asks for it (a diagnostic, not a deployable student)."""

    def forward(self, obs: torch.Tensor, stage: torch.Tensor | None = None):
        return super().forward(obs, obs[..., :0] if stage is None else stage)


@dataclass
class StudentModels:
    """The student's actor and the critic it trains with (see :func:`make_student_models`)."""

    actor: ProbabilisticActor
    actor_net: StudentNet | RecurrentStudentNet
    critic: TensorDictModule
    popart: PopArt | None
    critic_norm: ObsNorm | None  # the critic's, over the clean observation


def make_student_models(model_cfg: DictConfig, loss_cfg: DictConfig, env: TransformedEnv,
                        sees_stage: bool = False, recurrent_cells: int = 0, stage_loss_coeff: float = 0.0
                        ) -> StudentModels:
    """A decentralised actor over ``STUDENT_OBS`` (its own ObsNorm), with the distribution
    family, parameter head and critic that :func:`make_models` builds for the teacher (its
    teacher-shaped actor is dropped). With ``recurrent_cells`` the actor is a
    :class:`RecurrentStudentNet` (a GRU over the episode; ``stage_loss_coeff``: its
    training-only stage read-out).

    The critic reads the clean observation and stage one-hot: an asymmetric critic is
    standard in teacher-student training and only used in training, so the deployed
    student needs neither. The student reads no stage, so a teacher's stage-conditioned
    gripper ceiling (``model.grasp_open_min_prob``) is dropped."""
    model_cfg = model_cfg.copy()
    model_cfg.grasp_open_min_prob = 0.0
    base = make_models(model_cfg, loss_cfg, env)
    n_agents, n_in = env.observation_spec[STUDENT_OBS].shape[-2:]
    n_act = env.full_action_spec_unbatched[ACTION].shape[-1]
    n_stage = env.observation_spec[STAGE_ONE_HOT].shape[-1] if sees_stage else 0
    obs_norm = ObsNorm(n_in) if model_cfg.obs_norm else None
    if stage_loss_coeff and not recurrent_cells:
        raise ValueError(f"student.stage_loss_coeff={stage_loss_coeff} trains a GRU's state: "
                         "it needs student.recurrent_cells > 0")
    if recurrent_cells and sees_stage:
        raise ValueError("student.recurrent_cells and student.sees_stage are two answers to the unseen stage: pick one")
    if recurrent_cells:
        net = RecurrentStudentNet(n_in, 2 * n_act, n_agents, model_cfg.actor_cells, int(recurrent_cells),
                                  head=base.actor_net.head, obs_norm=obs_norm,
                                  n_stages=env.observation_spec[STAGE_ONE_HOT].shape[-1], stage_coeff=stage_loss_coeff)
        in_keys, out_keys = [STUDENT_OBS, HIDDEN, STEP_COUNT], [LOC, SCALE, HIDDEN_NEXT]
    else:
        net = StudentNet(n_in + n_stage, 2 * n_act, n_agents, False, model_cfg.actor_cells, head=base.actor_net.head,
                         obs_norm=obs_norm)
        in_keys = [STUDENT_OBS, STAGE_ONE_HOT] if sees_stage else [STUDENT_OBS]
        out_keys = [LOC, SCALE]
    family = base.actor.module[-1]  # the KL reads the teacher's parameters with this same family
    actor = ProbabilisticActor(
        TensorDictModule(net, in_keys=in_keys, out_keys=out_keys),
        in_keys=[LOC, SCALE], out_keys=[ACTION], distribution_class=family.distribution_class,
        distribution_kwargs=family.distribution_kwargs, return_log_prob=True, log_prob_key=LOG_PROB,
    )
    return StudentModels(actor, net, base.critic, base.popart, base.obs_norm)


def load_student_actor(cfg: DictConfig, env: TransformedEnv, ckpt: dict) -> ProbabilisticActor:
    """A student checkpoint's actor in ``env`` (built from ``cfg``); inputs that never moved
    on the training backend are folded when ``cfg.env.backend`` is another (as
    ``rollout.load_policy`` does for a teacher)."""
    models = make_student_models(cfg.model, cfg.loss, env, bool(cfg.student.sees_stage),
                                 int(cfg.student.recurrent_cells), float(cfg.student.stage_loss_coeff))
    models.actor.load_state_dict(ckpt["actor"])
    if cfg.env.backend != ckpt["cfg"]["env"]["backend"] and isinstance(models.actor_net.obs_norm, ObsNorm):
        fold_constant_inputs(models.actor_net.obs_norm, [models.actor_net])
    return models.actor.eval()


# Settings that shape the teacher's input: a student env must have the teacher's.
_TEACHER_ENV_KEYS = ("task", "num_robots", "handle_order", "handle_claim")


def check_teacher(cfg: DictConfig, teacher_cfg: DictConfig, path: str | Path) -> None:
    """Refuses a student configuration whose env or stage graph would feed the teacher
    (trained with ``teacher_cfg``) inputs it was not trained on, or whose gripper
    distribution differs from its own."""
    if cfg.env.task != "pnp":
        raise ValueError(f"distillation needs env.task='pnp' (the student's observation is built from its "
                         f"blocks), got {cfg.env.task!r}")
    for key in _TEACHER_ENV_KEYS:
        mine, theirs = cfg.env[key], teacher_cfg.env[key]
        if mine != theirs:
            raise ValueError(f"teacher {path} was trained with env.{key}={theirs!r}, this run has env.{key}={mine!r}")
    edges = [sorted(stage_graph(c.curriculum, "pnp").backward_edges) for c in (cfg, teacher_cfg)]
    added_ok = bool(cfg.distill.add_backward_edges) and set(edges[1]) <= set(edges[0])
    if edges[0] != edges[1] and not added_ok:
        raise ValueError(f"teacher {path} was trained with the backward edges {edges[1]} (curriculum.backward_edges="
                         f"{OmegaConf.to_container(teacher_cfg.curriculum)['backward_edges']}), this run has "
                         f"{edges[0]}: its stage one-hot would differ (distill.add_backward_edges=true allows "
                         "edges added to the teacher's)")
    if cfg.model.grasp_dist != teacher_cfg.model.grasp_dist:
        raise ValueError(f"teacher {path} has model.grasp_dist={teacher_cfg.model.grasp_dist!r}, this run "
                         f"{cfg.model.grasp_dist!r}: the KL needs one distribution family")


class Teacher:
    """The frozen teacher of the student configuration ``cfg`` (``distill.teacher``, checked
    against ``cfg``): its actor and ObsNorm from the checkpoint, never updated, in ``env``.

    :meth:`label` writes the teacher's distribution parameters on the clean observation
    and stage one-hot of a batch (``TEACHER_LOC``, ``TEACHER_SCALE``); ``actor`` acts on
    them (evaluation)."""

    def __init__(self, cfg: DictConfig, env: TransformedEnv):
        if cfg.distill.teacher is None:
            raise ValueError("distill.teacher is not set: pick distill_experiment=single|dual or give "
                             "distill.teacher=<checkpoint or run folder>")
        self.path = resolve_checkpoint(cfg.distill.teacher, cfg.runs_root)
        ckpt = load_checkpoint(self.path)
        if "distill" in ckpt["cfg"]:
            raise ValueError(f"distill.teacher {self.path} is a student's checkpoint, not a teacher's")
        self.cfg = migrate(ckpt["cfg"])
        check_teacher(cfg, self.cfg, self.path)
        self.critic_state = ckpt["critic"]
        models, self.folded = trained_models(ckpt, self.cfg, env, cfg.env.backend)  # it labels in the student's env
        self.actor = models.actor.requires_grad_(False).eval()
        self._label = TensorDictModule(models.actor_net, in_keys=[OBS, STAGE_ONE_HOT],
                                       out_keys=[TEACHER_LOC, TEACHER_SCALE])

    def to(self, device) -> Teacher:
        """The teacher where the student's update runs (it labels the batch there)."""
        self.actor.to(device)
        return self

    @torch.no_grad()
    def label(self, td: TensorDictBase) -> TensorDictBase:
        return self._label(td)


def evaluate_views(path: str | Path, trials: int, num_worlds: int, seed: int, progress: bool = False,
                   noise_scale: float | None = None, dropout_p: float | None = None,
                   **env_overrides) -> tuple[DictConfig, dict, dict[str, dict]]:
    """``trials`` deterministic episodes each of the student (its noisy observation), the
    teacher with the same noise on its own layout, and the teacher on clean observations
    (:data:`EVALUATIONS`), in evaluation envs (``rollout.evaluation_env_config``) built
    alike from the same seed. ``noise_scale`` and ``dropout_p`` replace the training noise
    model's (None keeps it). Returns the evaluation configuration, the student checkpoint
    and the trial records by run (paired: the same trials for each)."""
    ckpt = load_checkpoint(Path(path))
    cfg = distill_config(ckpt["cfg"])
    if noise_scale is not None:  # checked where the noise is built, as in training
        cfg.noise.scale = float(noise_scale)
    if dropout_p is not None:
        cfg.noise.dropout.p = float(dropout_p)
    evaluation_env_config(cfg.env, num_worlds, **env_overrides)
    results = {}
    for name, view in EVALUATIONS.items():
        seed_everything(seed)
        env = make_student_env(cfg, seed, view)
        if name == "student":
            actor = load_student_actor(cfg, env, ckpt)
        else:
            actor = Teacher(cfg, env).actor
        results[name] = run_trials(env, actor, trials, progress)
        env.close()
    return cfg, ckpt, results
