"""The distillation runner (paper Sec. III-C): the student acts on its own noisy
observations, the frozen teacher labels the same states from the clean observation and
stage, and PPO on the fixed-scale reward plus beta * KL to the teacher updates the student
(``pnp.losses.DistillationPPOLoss``).

Everything else is the teacher's trainer: collection (``collect``), the PPO update
(``ppo_update``), the loop with its logging, checkpoint timing and signals
(:meth:`Trainer.run`), checkpoints and their restoration. A run folder that holds a
checkpoint resumes from it, bit for bit (the noise and history state is in the env
transforms' state).
"""
from __future__ import annotations

from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from pnp.losses.distillation import DistillationPPOLoss
from pnp.training.checkpoint import load_checkpoint, load_module, seed_everything
from pnp.training.collect import MeanRollIn, collect, desync_episodes, episode_metrics
from pnp.training.config import changed_settings
from pnp.distill.config import distill_config
from pnp.training.keys import OBS, ROLL_IN, STUDENT_OBS, TEACHER_LOC, TEACHER_SCALE
from pnp.training.models import ObsNorm
from pnp.training.ppo import ppo_update
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


class DistillTrainer(Trainer):
    """One distillation run (or its resumption) in ``cfg.out_dir``; :meth:`Trainer.run`
    runs it. ``models`` are the student's, ``teacher`` the frozen labeller."""

    def __init__(self, cfg: DictConfig):  # builds what Trainer.run, checkpoint and _restore use
        cfg, ckpt = resume_config(cfg)
        check_config(cfg)
        self.cfg, self.out_dir = cfg, Path(cfg.out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.ckpt_path, self.metrics_path = self.out_dir / "checkpoint.pt", self.out_dir / "metrics.jsonl"
        seed_everything(int(cfg.seed))
        self.env = make_student_env(cfg, int(cfg.seed))
        self.teacher = Teacher(cfg, self.env)
        student = cfg.student
        self.models = make_student_models(cfg.model, cfg.loss, self.env, bool(student.sees_stage),
                                          int(student.recurrent_cells), float(student.stage_loss_coeff))
        self.loss = make_loss(cfg.loss, self.models, DistillationPPOLoss, beta=beta_at(cfg.distill, 0),
                              direction=str(cfg.distill.direction))
        self.loss.set_keys(teacher_loc=TEACHER_LOC, teacher_scale=TEACHER_SCALE)
        self.optim = torch.optim.Adam(self.loss.parameters(), lr=float(cfg.optim.lr))
        self.counters = {"iteration": 0, "frames": 0, "wall_s": 0.0}
        share = float(cfg.collect.roll_in_share)
        n_worlds = self.env.base_env.num_worlds
        self.roll_in = MeanRollIn(n_worlds, share, int(cfg.collect.roll_in_max_steps)) if share else None
        if ckpt is not None:
            self._restore(ckpt)
        else:
            self._start()
        self._open_log(ckpt, default_name=f"student_{cfg.env.backend}_{cfg.env.num_robots}r_s{cfg.seed}")

    def _norms(self) -> list[tuple[ObsNorm, tuple]]:
        """Each running normalisation with the observation it follows."""
        m = self.models
        pairs = [(m.actor_net.obs_norm, STUDENT_OBS), (m.critic_norm, OBS)]
        return [(n, key) for n, key in pairs if isinstance(n, ObsNorm)]

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
        self.carried = init_state(self.env.reset(), m.actor)
        if cfg.collect.desync_episodes:
            self.carried = desync_episodes(self.carried, cfg.env.max_episode_steps)
        for norm, key in self._norms():  # first statistics from the initial layouts
            if key == STUDENT_OBS or not cfg.distill.critic_from_teacher:
                norm.update(self.carried[key])

    def iteration(self, steps: int) -> dict:
        """Collect with the student, label with the teacher, update, log one iteration."""
        beta = self.loss.beta = beta_at(self.cfg.distill, self.counters["iteration"])
        batch, self.carried = collect(self.env, self.models.actor, self.carried, steps, self.roll_in)
        self.teacher.label(batch)
        losses = ppo_update(batch, self.loss, self.optim, self.cfg)
        for norm, key in self._norms():
            norm.update(batch[key])
        self.counters["iteration"] += 1
        self.counters["frames"] += batch.numel()
        extra = {"roll_in_frames": float(batch[ROLL_IN].float().mean())} if self.roll_in is not None else {}
        row = {**self.counters, **episode_metrics(batch), **losses, "beta": beta, **extra}
        return row


def distill(cfg: DictConfig) -> dict:
    """Run (or resume) a distillation; see :meth:`Trainer.run`."""
    return DistillTrainer(cfg).run()
