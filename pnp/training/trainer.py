"""The on-policy runner: builds env, models, loss and optimiser from a :class:`TrainConfig`,
collects, updates, logs, checkpoints, resumes bit for bit and warm-starts.

A resumed run continues in its checkpoint's folder: checkpoints are taken at iteration
boundaries and hold everything that moves (weights, Adam, curriculum, env state, the
carried tensordict, all RNGs).
"""
from __future__ import annotations

import json
import math
import shutil
import signal
import threading
import time
from pathlib import Path
from typing import Callable

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from torchrl.record.loggers import CSVLogger, Logger, WandbLogger
from tqdm import tqdm

from pnp.losses.mappo import PopArtMAPPOLoss
from pnp.baselines.per_stage import baseline_loss, method_hooks, use_baseline_schedule
from pnp.training.checkpoint import (
    adapt_curriculum, load_checkpoint, load_module, load_optimiser, resolve_checkpoint, restore_training_state, rng_state,
    save_checkpoint, seed_everything, set_rng_state,
)
from pnp.training.collect import collect, desync_episodes, episode_metrics
from pnp.training.device import training_device
from pnp.training.migration import changed_settings, migrate
from pnp.training.keys import (
    ACTION, ADVANTAGE, LOC, LOG_PROB, OBS, REWARD, SCALE, VALUE, VALUE_TARGET,
)
from pnp.training.models import ObsNorm, fold_constant_inputs, make_models
from pnp.training.plots import plot_training
from pnp.training.provenance import launch_record
from pnp.training.ppo import ppo_update
from pnp.training.progress import RunProgress
from pnp.training.threads import available_cores, torch_threads
from pnp.training.hooks import RollIns, RunHook
from pnp.training.tasks import make_env, schedule_of

# Keys a resumed run takes from the command line; everything else comes from the checkpoint.
# env.nthread too: MuJoCo steps each world on its own, so the thread count does not change
# the numbers, and a run may move to a machine with fewer cores (torch's threads likewise,
# though its sums may round differently, and the device likewise); the logger's name names only.
RESUME_OVERRIDES = ("total_iterations", "max_wall_hours", "checkpoint_every_min", "snapshot_every", "progress",
                    "env.nthread", "threads.collect", "threads.update", "device", "logger.exp_name")


def make_loss(loss_cfg: DictConfig, models, loss_cls: type[PopArtMAPPOLoss] = PopArtMAPPOLoss,
              **loss_kwargs) -> PopArtMAPPOLoss:
    """The MAPPO loss of ``loss_cfg`` (or ``loss_cls``, a subclass, with its ``loss_kwargs``)."""
    loss = loss_cls(models.actor, models.critic, models.popart, clip_epsilon=float(loss_cfg.clip_epsilon),
                    entropy_coeff=float(loss_cfg.entropy_coeff), critic_coeff=float(loss_cfg.critic_coeff),
                    loss_critic_type=str(loss_cfg.loss_critic_type), **loss_kwargs)
    loss.set_keys(reward=REWARD, action=ACTION, sample_log_prob=LOG_PROB, value=VALUE, advantage=ADVANTAGE,
                  value_target=VALUE_TARGET, done="done", terminated="terminated", loc=LOC, scale=SCALE)
    loss.make_value_estimator(gamma=float(loss_cfg.gamma), lmbda=float(loss_cfg.lmbda))
    return loss


def make_training(cfg: DictConfig):
    """``(env, models, loss)`` of a run configuration: the env with the per-stage baselines'
    reward schedule (``model.per_stage``), their models and their loss, or ours. One place,
    so that the trainer, the profiler and Table I's parameter count build the same thing."""
    env = make_env(cfg.env, cfg.curriculum, int(cfg.seed))
    use_baseline_schedule(env, cfg)
    models = make_models(cfg.model, cfg.loss, env)
    loss_cls, loss_kwargs = baseline_loss(cfg)
    return env, models, make_loss(cfg.loss, models, loss_cls, **loss_kwargs)


def resume_config(cfg: DictConfig) -> tuple[DictConfig, dict | None]:
    """The configuration to run: ``cfg`` itself, or with ``resume`` set, the checkpoint's
    (migrated to the schema) with only :data:`RESUME_OVERRIDES` taken from ``cfg``."""
    if cfg.resume in (None, False) or str(cfg.resume).lower() in ("false", "none", ""):
        return cfg, None
    path = resolve_checkpoint(cfg.resume, cfg.runs_root)
    ckpt = load_checkpoint(path)
    saved = migrate(ckpt["cfg"])
    for k in RESUME_OVERRIDES:
        OmegaConf.update(saved, k, OmegaConf.select(cfg, k), merge=False)
    saved.out_dir, saved.resume = str(path.parent), str(path)
    return saved, ckpt


# Keys that may differ between a run's start and a command that continues it in its folder.
RESUMABLE = frozenset(RESUME_OVERRIDES) | {"out_dir", "resume", "warm_start", "warm_start_curriculum",
                                           "warm_start_fold_constant"}


def resume_in_place(cfg: DictConfig) -> DictConfig:
    """Rerunning the same command continues its run: an ``out_dir`` that holds a checkpoint is
    resumed, never restarted over (which would overwrite its metrics). A folder holds one run:
    a command whose settings differ from that run's (other than :data:`RESUMABLE`) is refused,
    naming the keys, since a resume would silently run the old settings."""
    path = Path(cfg.out_dir) / "checkpoint.pt"
    if cfg.resume or not path.exists():
        return cfg
    changed = changed_settings(cfg, migrate(load_checkpoint(path)["cfg"]), RESUMABLE)
    if changed:
        raise ValueError(f"out_dir={cfg.out_dir} holds a run made with other settings (key: (that run, this command)) "
                         f"{changed}: choose another out_dir, or continue that run with its own settings "
                         f"(resume={cfg.out_dir})")
    cfg.resume = str(path)
    return cfg


def launches(ckpt: dict | None) -> list[dict]:
    """Every start and resume of a run (command, commit, machine, date): a run that crosses
    sessions may cross machines too, and the same seed differs between CPUs."""
    return [*((ckpt or {}).get("launches", [])), launch_record()]


def make_logger(cfg: DictConfig, out_dir: Path, wandb_id: str | None, default_name: str | None = None) -> Logger:
    """The run's logger, named ``logger.exp_name``, else ``default_name``, else by backend,
    robot count, schedule and seed."""
    name = (cfg.logger.exp_name or default_name
            or f"{cfg.env.backend}_{cfg.env.num_robots}r_{cfg.curriculum.schedule}_s{cfg.seed}")
    if cfg.logger.backend == "csv":
        return CSVLogger(name, log_dir=str(out_dir))
    if cfg.logger.backend == "wandb":
        # config= at init: offline runs drop config updates made after init.
        return WandbLogger(name, offline=bool(cfg.logger.offline), save_dir=str(out_dir), project=cfg.logger.project,
                           id=wandb_id, config=OmegaConf.to_container(cfg, resolve=True, enum_to_str=True))
    raise ValueError(f"logger.backend must be 'wandb' or 'csv', got {cfg.logger.backend!r}")


class StopOnSignal:
    """SIGTERM/SIGINT finish the current iteration, checkpoint and stop (a second one kills)."""

    def __init__(self):
        self.received = False
        self._old = {}
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGTERM, signal.SIGINT):
                self._old[sig] = signal.signal(sig, self._handle)

    def _handle(self, sig, frame):
        if self.received:
            self.restore()
            signal.raise_signal(sig)
        self.received = True

    def restore(self):
        for sig, old in self._old.items():
            signal.signal(sig, old)
        self._old = {}


def truncate_metrics(path: Path, iteration: int) -> None:
    """Drop lines logged after the checkpoint (a run killed between checkpoints)."""
    if path.is_file():
        rows = [r for r in path.read_text().splitlines() if r and json.loads(r)["iteration"] <= iteration]
        path.write_text("".join(r + "\n" for r in rows))


class Trainer:
    """One training run (or its resumption) in ``cfg.out_dir``: the runner. What only some
    runs do is in its ``hooks`` (``pnp.training.hooks``): roll-ins, a baseline's schedule,
    a student's teacher."""

    def __init__(self, cfg: DictConfig):
        cfg, ckpt = self.resume_config(cfg)
        if cfg.out_dir is None:
            raise ValueError("out_dir is not set (the hydra entry point sets it to the run folder)")
        if ckpt is None and (Path(cfg.out_dir) / "checkpoint.pt").is_file():
            # A fresh start would truncate the run's metrics and soon overwrite its checkpoint.
            raise ValueError(f"out_dir={cfg.out_dir} holds a run (checkpoint.pt): resume={cfg.out_dir} continues it; "
                             "to start over, use another out_dir or delete that one")
        self.cfg, self.out_dir = cfg, Path(cfg.out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.ckpt_path, self.metrics_path = self.out_dir / "checkpoint.pt", self.out_dir / "metrics.jsonl"
        seed_everything(int(cfg.seed))
        self.threads = torch_threads(cfg.threads)
        tqdm.write(f"torch threads: {self.threads['collect']} collecting, {self.threads['update']} in the update "
              f"({available_cores()} cores available; cfg.threads)")
        self.device = training_device(cfg.device)
        self.build()
        self.to_device()
        self.optim = torch.optim.Adam(self.loss.parameters(), lr=float(cfg.optim.lr))
        self.counters = {"iteration": 0, "frames": 0, "wall_s": 0.0}
        share = float(cfg.collect.roll_in_share)
        roll_ins = RollIns(self.env.base_env.num_worlds, share, int(cfg.collect.roll_in_max_steps)) if share else None
        self.roll_in = roll_ins.roll_in if roll_ins else None  # collection reads it
        self.hooks = ([roll_ins] if roll_ins else []) + self.method_hooks()
        if ckpt is not None:
            self._restore(ckpt)
        else:
            self._start()
        for hook in self.hooks:
            hook.on_ready(self)
        self._open_log(ckpt, self.log_name())

    # What a kind of run changes (the distillation overrides these) --------------------------
    @staticmethod
    def resume_config(cfg: DictConfig) -> tuple[DictConfig, dict | None]:
        return resume_config(cfg)

    def build(self) -> None:
        """``env``, ``models`` and ``loss`` of the run."""
        self.env, self.models, self.loss = make_training(self.cfg)

    def to_device(self) -> None:
        """The networks to ``cfg.device``, before the optimiser takes their parameters: the
        loss holds the actor and the critic (PopArt and ObsNorm inside them) as they are."""
        self.loss.to(self.device)

    def method_hooks(self) -> list[RunHook]:
        return method_hooks(self.cfg, self)

    def log_name(self) -> str | None:
        return None

    def norms(self) -> list[tuple[ObsNorm, str]]:
        """Each running observation normalisation with the batch entry it follows."""
        return [(self.models.obs_norm, OBS)] if self.models.obs_norm is not None else []

    def metrics(self, batch: TensorDictBase) -> dict:
        """The curriculum's scales rho_j per reward term, when the schedule has them."""
        schedule = schedule_of(self.env)
        rho = schedule.rho_by_term() if hasattr(schedule, "rho_by_term") else {}
        return {f"rho/{k}": v for k, v in rho.items()}

    def _open_log(self, ckpt: dict | None, default_name: str | None = None) -> None:
        """The run's launches and logger (the same wandb run on a resume)."""
        self.wandb_id = ckpt.get("wandb_id") if ckpt else None
        self.launches = launches(ckpt)
        self.logger = make_logger(self.cfg, self.out_dir, self.wandb_id, default_name)
        if self.cfg.logger.backend == "wandb":
            self.wandb_id = self.logger.experiment.id

    def _restore(self, ckpt: dict) -> None:
        self.carried = restore_training_state(ckpt, self.env, self.models, self.optim)
        self.counters = dict(ckpt["counters"])
        set_rng_state(ckpt["rng"])
        for hook in self.hooks:
            if hook.key is not None and hook.key in ckpt:
                hook.load_state_dict(ckpt[hook.key])
        truncate_metrics(self.metrics_path, self.counters["iteration"])

    def _start(self) -> None:
        cfg, m = self.cfg, self.models
        truncate_metrics(self.metrics_path, 0)  # a reused folder starts a fresh log
        if cfg.warm_start:
            init = load_checkpoint(resolve_checkpoint(cfg.warm_start, cfg.runs_root))
            load_module(m.actor, init["actor"])
            widened = load_module(m.critic, init["critic"])  # a single-robot critic into the dual task
            if widened:
                print(f"warm start: widened {widened} with zero weights on the neighbour's inputs")
            # Adam's moments and the adapted lr too: a fresh Adam at optim.lr took a sharp
            # (entropy -19) policy to KL 74 in its first iteration (measured).
            load_optimiser(self.optim, init["optim"])
            if cfg.optim.lr_schedule == "fixed":  # a fixed lr is this run's, not the adapted one it carried
                for group in self.optim.param_groups:
                    group["lr"] = float(cfg.optim.lr)
            for hook in self.hooks:
                hook.on_warm_start(self, init)
            if m.obs_norm is not None and cfg.warm_start_fold_constant:
                print(f"warm start: folded constant observation entries "
                      f"{fold_constant_inputs(m.obs_norm, [m.actor_net, m.critic_net])}")
            if cfg.warm_start_curriculum:  # rho_j as they were: no reward-scale shock
                base = self.env.base_env
                self.env.transform.load_state_dict(adapt_curriculum(init["curriculum"], base.num_worlds,
                                                                    base.num_robots))
        self.carried = self.env.reset()
        if cfg.curriculum.start_final:
            schedule = schedule_of(self.env)
            if not hasattr(schedule, "enter_final"):
                raise ValueError(f"curriculum.start_final needs the dynamic schedule, not {cfg.curriculum.schedule!r}")
            schedule.enter_final()
        if cfg.collect.desync_episodes:
            self.carried = desync_episodes(self.carried, cfg.env.max_episode_steps)
        if m.obs_norm is not None and not cfg.warm_start:
            m.obs_norm.update(self.carried[OBS])  # first statistics from the initial layouts

    def checkpoint(self) -> None:
        m = self.models
        save_checkpoint(self.ckpt_path, {
            "cfg": OmegaConf.to_container(self.cfg, resolve=True, enum_to_str=True), "counters": dict(self.counters),
            "actor": m.actor.state_dict(), "critic": m.critic.state_dict(), "optim": self.optim.state_dict(),
            "curriculum": self.env.transform.state_dict(), "env": self.env.base_env.get_state(),
            "carried": self.carried, "rng": rng_state(), "wandb_id": self.wandb_id,
            "launches": self.launches,
            **{hook.key: hook.state_dict() for hook in self.hooks if hook.key is not None},
        })

    def snapshot(self) -> Path:
        """A copy of the checkpoint just written, named by its iteration."""
        path = self.out_dir / "snapshots" / f"iteration_{self.counters['iteration']:06d}.pt"
        path.parent.mkdir(exist_ok=True)
        shutil.copyfile(self.ckpt_path, path)
        return path

    def iteration(self, steps: int) -> dict:
        """Collect, update, log one iteration; returns its metrics row."""
        for hook in self.hooks:
            hook.before_collect(self)
        torch.set_num_threads(self.threads["collect"])
        batch, self.carried = collect(self.env, self.models.actor, self.carried, steps, self.roll_in)
        for hook in self.hooks:
            hook.on_batch(self, batch)
        torch.set_num_threads(self.threads["update"])
        losses = ppo_update(batch, self.loss, self.optim, self.cfg)
        for norm, key in self.norms():
            norm.update(batch[key])
        self.counters["iteration"] += 1
        self.counters["frames"] += batch.numel()
        row = {**self.counters, **episode_metrics(batch), **losses, **self.metrics(batch)}
        for hook in self.hooks:
            row.update(hook.on_row(self, batch, row))
        return row

    def run(self, stop_when: Callable[[dict], bool] | None = None, progress=None) -> dict:
        """Train to ``total_iterations`` (or the wall-time limit, a signal, or until
        ``stop_when(row)`` holds after an iteration); returns the run folder, checkpoint
        path, how it stopped and the last metrics. ``progress``: what each metrics row is shown
        on (a pipeline's ``PipelineProgress``) instead of this run's own bar."""
        cfg = self.cfg
        steps = max(1, int(cfg.collect.frames_per_batch) // self.env.base_env.num_worlds)
        total, every_s = int(cfg.total_iterations), 60.0 * float(cfg.checkpoint_every_min)
        max_wall = math.inf if cfg.max_wall_hours is None else 3600.0 * float(cfg.max_wall_hours)
        wall0, t0 = self.counters["wall_s"], time.monotonic()
        last_ckpt, row, by_rule = t0, {}, False
        own_bar = progress is None
        if own_bar:
            progress = RunProgress(total, self.counters["iteration"], bool(cfg.progress))
        stop_signal = StopOnSignal()
        try:
            while self.counters["iteration"] < total:
                row = self.iteration(steps)
                self.counters["wall_s"] = row["wall_s"] = wall0 + time.monotonic() - t0
                with self.metrics_path.open("a") as f:
                    f.write(json.dumps(row) + "\n")
                self.logger.log_metrics({k: v for k, v in row.items() if math.isfinite(v)},
                                        step=self.counters["iteration"])
                by_rule = stop_when is not None and stop_when(row)
                progress.update(row)
                stop = (self.counters["iteration"] >= total or self.counters["wall_s"] >= max_wall
                        or stop_signal.received or by_rule)
                snap = int(cfg.snapshot_every) > 0 and self.counters["iteration"] % int(cfg.snapshot_every) == 0
                if stop or snap or time.monotonic() - last_ckpt >= every_s:
                    self.checkpoint()
                    last_ckpt = time.monotonic()
                if snap:
                    self.snapshot()
                if stop:
                    break
            if not self.ckpt_path.is_file():  # total already reached at start
                self.checkpoint()
        finally:
            stop_signal.restore()
        if own_bar:
            progress.close()
        plot_training(self.metrics_path, self.out_dir)
        if cfg.logger.backend == "wandb":
            self.logger.experiment.finish()
        self.env.close()
        return {"out_dir": str(self.out_dir), "checkpoint": str(self.ckpt_path),
                "stopped_by_signal": stop_signal.received, "stopped_by_rule": by_rule, **row}


def train(cfg: DictConfig) -> dict:
    """Run (or resume) a training; see :meth:`Trainer.run`."""
    return Trainer(cfg).run()
