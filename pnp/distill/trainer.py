"""The distillation runner (paper Sec. III-C): the student acts on its own noisy
observations, the frozen teacher labels the same states from the clean observation and
stage, and PPO on the fixed-scale reward plus beta * KL to the teacher updates the student
(``pnp.losses.DistillationPPOLoss``).

Everything else is the teacher's runner (:class:`~pnp.training.trainer.Trainer`): collection,
the PPO update, the loop with its logging, checkpoint timing and signals, checkpoints and
their restoration; the teacher's labels and the KL weight are a hook on it. A run folder that holds a
checkpoint resumes from it, bit for bit (the noise and history state is in the env
transforms' state).
"""
from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from pnp.losses.distillation import DistillationPPOLoss
from pnp.training.checkpoint import load_checkpoint, load_module, resolve_checkpoint
from pnp.training.collect import desync_episodes
from pnp.training.hooks import RunHook
from pnp.training.migration import changed_settings
from pnp.distill.config import distill_config
from pnp.training.keys import OBS, STUDENT_OBS, TEACHER_LOC, TEACHER_SCALE
from pnp.training.models import ObsNorm
from pnp.training.recurrent import init_state
from pnp.distill.student import Teacher, make_student_env, make_student_models
from pnp.training.trainer import RESUME_OVERRIDES, Trainer, make_loss, truncate_metrics


def resume_config(cfg: DictConfig) -> tuple[DictConfig, dict | None]:
    """``cfg``, or where ``out_dir`` holds a checkpoint, the checkpoint's configuration with
    only the trainer's ``RESUME_OVERRIDES`` taken from ``cfg``."""
    if cfg.out_dir is None:
        raise ValueError("out_dir is not set (the hydra entry point sets it to the run folder)")
    path = Path(cfg.out_dir) / "checkpoint.pt"
    if not path.is_file():
        return cfg, None
    ckpt = load_checkpoint(path)
    saved = distill_config(ckpt["cfg"])
    changed = changed_settings(cfg, saved, {*RESUME_OVERRIDES, "out_dir"})
    if changed:  # a resume runs the checkpoint's settings: the edit would be silently ignored
        raise ValueError(f"{path} was started with other settings (key: (then, now)) {changed}; "
                         "restore them or use another out_dir")
    for k in RESUME_OVERRIDES:
        OmegaConf.update(saved, k, OmegaConf.select(cfg, k), merge=False)
    saved.out_dir = str(path.parent)
    return saved, ckpt


def beta_at(kl: DictConfig, iteration: int) -> float:
    """``distill.beta``, moved linearly to ``distill.beta_final`` over ``anneal_iterations``."""
    if kl.beta_final is None:
        return float(kl.beta)
    frac = min(1.0, iteration / int(kl.anneal_iterations))
    return float(kl.beta) + (float(kl.beta_final) - float(kl.beta)) * frac


def check_config(cfg: DictConfig) -> None:
    if cfg.curriculum.schedule != "fixed":
        raise ValueError(f"the student trains on fixed reward scales (paper Sec. III-C): curriculum.schedule must "
                         f"be 'fixed', got {cfg.curriculum.schedule!r}")
    kl = cfg.distill
    if kl.beta < 0 or (kl.beta_final is not None and kl.beta_final < 0):
        raise ValueError(f"distill.beta and distill.beta_final must be >= 0, got {kl.beta} and {kl.beta_final}")
    if kl.beta_final is not None and kl.anneal_iterations < 1:
        raise ValueError(f"distill.beta_final={kl.beta_final} needs distill.anneal_iterations >= 1, "
                         f"got {kl.anneal_iterations}")


class TeacherLabels(RunHook):
    """The frozen teacher labels each batch from the clean observation and stage, and the KL
    weight follows its schedule (``distill.beta`` to ``beta_final``)."""

    def __init__(self, teacher: Teacher, kl: DictConfig):
        self.teacher, self.kl = teacher, kl

    def on_ready(self, runner) -> None:
        self.teacher.to(runner.device)

    def before_collect(self, runner) -> None:
        runner.loss.beta = beta_at(self.kl, runner.counters["iteration"])

    def on_batch(self, runner, batch) -> None:
        self.teacher.label(batch)

    def on_row(self, runner, batch, row: dict) -> dict:
        return {"beta": runner.loss.beta}


class DistillTrainer(Trainer):
    """One distillation run (or its resumption) in ``cfg.out_dir``: the runner with the
    student's env, models and loss and the teacher's labels as a hook."""

    @staticmethod
    def resume_config(cfg: DictConfig) -> tuple[DictConfig, dict | None]:
        cfg, ckpt = resume_config(cfg)
        check_config(cfg)
        return cfg, ckpt

    def build(self) -> None:
        cfg = self.cfg
        self.env = make_student_env(cfg, int(cfg.seed))
        self.teacher = Teacher(cfg, self.env)
        student = cfg.student
        self.models = make_student_models(cfg.model, cfg.loss, self.env, bool(student.sees_stage),
                                          int(student.recurrent_cells), float(student.stage_loss_coeff))
        self.loss = make_loss(cfg.loss, self.models, DistillationPPOLoss, beta=beta_at(cfg.distill, 0),
                              direction=str(cfg.distill.direction))
        self.loss.set_keys(teacher_loc=TEACHER_LOC, teacher_scale=TEACHER_SCALE)

    def method_hooks(self) -> list[RunHook]:
        return [TeacherLabels(self.teacher, self.cfg.distill)]

    def log_name(self) -> str:
        cfg = self.cfg
        return f"student_{cfg.env.backend}_{cfg.env.num_robots}r_s{cfg.seed}"

    def norms(self) -> list[tuple[ObsNorm, tuple]]:
        m = self.models
        pairs = [(m.actor_net.obs_norm, STUDENT_OBS), (m.critic_norm, OBS)]
        return [(n, key) for n, key in pairs if isinstance(n, ObsNorm)]

    def metrics(self, batch) -> dict:
        return {}  # fixed scales: no rho to log

    def _start(self) -> None:
        cfg, m = self.cfg, self.models
        truncate_metrics(self.metrics_path, 0)  # a reused folder starts a fresh log
        if cfg.distill.critic_from_teacher:
            mine, theirs = (cfg.model.critic_cells, cfg.loss.value_norm, cfg.model.obs_norm), self.teacher.cfg
            if mine != (theirs.model.critic_cells, theirs.loss.value_norm, theirs.model.obs_norm):
                raise ValueError(
                    f"distill.critic_from_teacher needs the teacher's model.critic_cells, loss.value_norm and "
                    f"model.obs_norm ({list(theirs.model.critic_cells)}, {theirs.loss.value_norm!r}, "
                    f"{theirs.model.obs_norm}), this run has ({list(mine[0])}, {mine[1]!r}, {mine[2]})")
            load_module(m.critic, self.teacher.critic_state)
        if cfg.warm_start:  # a student moved to a new teacher or env (legs): its actor and input statistics
            init = load_checkpoint(resolve_checkpoint(cfg.warm_start, cfg.runs_root))
            if "distill" not in init["cfg"]:
                raise ValueError(f"warm_start={cfg.warm_start!r} holds a teacher; a student warm-starts from a "
                                 f"student's checkpoint (a teacher is distill.teacher)")
            load_module(m.actor, init["actor"])
        self.carried = init_state(self.env.reset(), m.actor)
        if cfg.collect.desync_episodes:
            self.carried = desync_episodes(self.carried, cfg.env.max_episode_steps)
        for norm, key in self.norms():  # first statistics from the initial layouts
            if (key == STUDENT_OBS and not cfg.warm_start) or (key == OBS and not cfg.distill.critic_from_teacher):
                norm.update(self.carried[key])


def distill(cfg: DictConfig) -> dict:
    """Run (or resume) a distillation; see :meth:`Trainer.run`."""
    return DistillTrainer(cfg).run()
