"""Train the high-level teacher with MAPPO and the dynamic reward curriculum (paper Sec. III).

    python recipes/train.py                                  # the paper's setting on MuJoCo
    python recipes/train.py env.backend=kinematic env.num_worlds=256 env.max_episode_steps=150
    python recipes/train.py curriculum.schedule=liu_max logger.backend=csv
    python recipes/train.py resume=true                      # newest runs/**/checkpoint.pt
    python recipes/train.py warm_start=runs/<run>/checkpoint.pt

The run folder (``runs/train_<date>`` unless ``out_dir=``) receives ``checkpoint.pt``
(every ``checkpoint_every_min`` minutes and at the end), ``metrics.jsonl`` (one line per
iteration), the training plots (``*.png``) and the logger's files (wandb offline or csv).
A resumed run continues in its checkpoint's folder, bit for bit: checkpoints are taken at
iteration boundaries and hold everything that moves (weights, Adam, curriculum, env state,
the carried tensordict, all RNGs).
"""
from __future__ import annotations

import json
import math
import signal
import sys
import threading
import time
from collections import defaultdict
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf
from torchrl.record.loggers import CSVLogger, WandbLogger
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import (  # noqa: E402
    OBS, ROLL_IN, MeanRollIn, collect, episode_metrics, fold_constant_inputs, load_checkpoint, make_env, make_loss,
    make_models, policy_kl, reach_loss, resolve_checkpoint, rng_state, save_checkpoint, schedule_of, seed_everything,
    set_rng_state,
)
from plots import plot_training  # noqa: E402
from _warm_start import adapt_curriculum, load_module, load_optimiser  # noqa: E402

# Keys a resumed run takes from the command line; everything else comes from the checkpoint.
# env.nthread too: a run moved to a machine with fewer cores (MuJoCo steps each world on its own, so
# the thread count does not change the numbers).
RESUME_OVERRIDES = ("total_iterations", "max_wall_hours", "checkpoint_every_min", "progress", "env.nthread")
LOGGED_LOSSES = ("loss_objective", "loss_critic", "loss_entropy", "entropy", "explained_variance", "clip_fraction",
                 "kl_approx")


def ppo_update(batch, loss, optim, popart, cfg: DictConfig) -> dict[str, float]:
    """GAE once per iteration, PopArt statistics once, then epochs of shuffled minibatches."""
    with torch.no_grad():
        loss.value_estimator(batch)
    if popart is not None:
        popart.update(batch.get(loss.tensor_keys.value_target))
    flat = batch.reshape(-1)
    if ROLL_IN in flat.keys():  # roll-in actions were the mean, not drawn: no policy gradient from them
        flat = flat[~flat[ROLL_IN].reshape(-1)]
    params = [p for g in optim.param_groups for p in g["params"]]
    sums, n = defaultdict(float), 0
    reach_coeff = float(cfg.loss.get("reach_coeff", 0.0))
    frames = flat.batch_size[0]  # not numel(): a TensorDict of batch [0] reports 1
    for _ in range(int(cfg.collect.num_epochs) if frames else 0):
        for idx in torch.randperm(frames).split(int(cfg.collect.minibatch_size)):
            mb = flat[idx]
            kl = policy_kl(loss.actor_network, mb)  # before the loss, which may rewrite loc/scale
            _adapt_lr(optim, kl, cfg.optim)
            out = loss(mb)
            total = out["loss_objective"] + out["loss_critic"] + out["loss_entropy"]
            if reach_coeff > 0:
                reach = reach_loss(loss.actor_network, mb)
                total = total + reach_coeff * reach
                sums["ee_out_of_reach"] += float(reach.detach())
            optim.zero_grad(set_to_none=True)
            total.backward()
            sums["grad_norm"] += float(torch.nn.utils.clip_grad_norm_(params, float(cfg.optim.max_grad_norm)))
            optim.step()
            for k in LOGGED_LOSSES:
                if k in out.keys():
                    sums[k] += float(out[k].detach().float().mean())
            sums["kl"] += kl
            n += 1
    # n == 0 (every frame a roll-in) leaves no sums to divide.
    return {**{f"train/{k}": v / n for k, v in sums.items()}, "train/lr": optim.param_groups[0]["lr"]}


def desync_episodes(carried, max_steps):
    """Start each world's first episode at a random step of the ``max_steps`` limit.

    Why: every world resets at once at the start and episodes have a fixed length (no
    termination on success), so without this all worlds stay in phase: each batch of
    T steps holds the same 1-2 s of every episode (all approach, then all grasp ...) and
    consecutive PPO updates see different parts of the task (as rsl_rl, which starts
    episode clocks at random). Only the first episode of each world is cut short.
    """
    if not max_steps:
        raise ValueError("collect.desync_episodes needs env.max_episode_steps (the limit whose clock it offsets)")
    count = carried["step_count"]
    carried["step_count"] = torch.randint_like(count, 0, int(max_steps))
    return carried


def _adapt_lr(optim, kl: float, ocfg: DictConfig) -> None:
    """KL-adaptive step size (as rsl_rl): a fixed lr is too large or too small as the policy sharpens."""
    if ocfg.lr_schedule != "adaptive":
        return
    for g in optim.param_groups:
        if kl > 2.0 * ocfg.desired_kl:
            g["lr"] = max(g["lr"] / 1.5, float(ocfg.min_lr))
        elif kl < 0.5 * ocfg.desired_kl:
            g["lr"] = min(g["lr"] * 1.5, float(ocfg.max_lr))


def _resume_cfg(cfg: DictConfig) -> tuple[DictConfig, dict | None]:
    if cfg.resume in (None, False) or str(cfg.resume).lower() in ("false", "none", ""):
        return cfg, None
    path = resolve_checkpoint(cfg.resume, cfg.runs_root)
    ckpt = load_checkpoint(path)
    saved = OmegaConf.create(ckpt["cfg"])
    for k in RESUME_OVERRIDES:
        OmegaConf.update(saved, k, OmegaConf.select(cfg, k), merge=False)
    saved.out_dir, saved.resume = str(path.parent), str(path)
    return saved, ckpt


def _make_logger(cfg: DictConfig, out_dir: Path, wandb_id: str | None):
    name = cfg.logger.exp_name or f"{cfg.env.backend}_{cfg.env.num_robots}r_{cfg.curriculum.schedule}_s{cfg.seed}"
    if cfg.logger.backend == "csv":
        return CSVLogger(name, log_dir=str(out_dir))
    if cfg.logger.backend == "wandb":
        # config= at init: offline runs drop config updates made after init.
        return WandbLogger(name, offline=bool(cfg.logger.offline), save_dir=str(out_dir), project=cfg.logger.project,
                           id=wandb_id, config=OmegaConf.to_container(cfg, resolve=True))
    raise ValueError(f"logger.backend must be 'wandb' or 'csv', got {cfg.logger.backend!r}")


class _StopOnSignal:
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


def _truncate_metrics(path: Path, iteration: int) -> None:
    """Drop lines logged after the checkpoint (a run killed between checkpoints)."""
    if path.is_file():
        rows = [r for r in path.read_text().splitlines() if r and json.loads(r)["iteration"] <= iteration]
        path.write_text("".join(r + "\n" for r in rows))


def train(cfg: DictConfig) -> dict:
    """Run (or resume) a training; returns the run folder, checkpoint path and last metrics."""
    cfg, ckpt = _resume_cfg(cfg)
    if cfg.out_dir is None:
        raise ValueError("out_dir is not set (the hydra entry point sets it to the run folder)")
    out_dir = Path(cfg.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    ckpt_path, metrics_path = out_dir / "checkpoint.pt", out_dir / "metrics.jsonl"
    seed_everything(int(cfg.seed))
    env = make_env(cfg.env, cfg.curriculum, int(cfg.seed))
    actor, critic, popart, obs_norm = make_models(cfg.model, env, cfg.loss.value_norm, float(cfg.loss.popart_beta))
    loss = make_loss(cfg.loss, actor, critic, popart)
    optim = torch.optim.Adam(loss.parameters(), lr=float(cfg.optim.lr))
    counters = {"iteration": 0, "frames": 0, "wall_s": 0.0}
    share = float(cfg.collect.get("roll_in_share", 0.0))
    roll_in = (MeanRollIn(env.base_env.num_worlds, share, int(cfg.collect.get("roll_in_max_steps", 1)))
               if share else None)
    if ckpt is not None:
        actor.load_state_dict(ckpt["actor"])
        critic.load_state_dict(ckpt["critic"])
        optim.load_state_dict(ckpt["optim"])
        env.transform.load_state_dict(ckpt["curriculum"])
        env.base_env.set_state(ckpt["env"])
        carried = ckpt["carried"]
        counters = dict(ckpt["counters"])
        set_rng_state(ckpt["rng"])
        if roll_in is not None and "roll_in" in ckpt:
            roll_in.length.copy_(ckpt["roll_in"])
        _truncate_metrics(metrics_path, counters["iteration"])
    else:
        _truncate_metrics(metrics_path, 0)  # a reused folder starts a fresh log
        if cfg.warm_start:
            init = load_checkpoint(resolve_checkpoint(cfg.warm_start, cfg.runs_root))
            load_module(actor, init["actor"])
            widened = load_module(critic, init["critic"])  # a single-robot critic into the dual task
            if widened:
                print(f"warm start: widened {widened} with zero weights on the neighbour's inputs")
            # Adam's moments and the adapted lr too: a fresh Adam at optim.lr took a sharp
            # (entropy -19) policy to KL 74 in its first iteration (measured).
            load_optimiser(optim, init["optim"])
            if obs_norm is not None and cfg.get("warm_start_fold_constant"):
                folded = fold_constant_inputs(obs_norm, [actor.module[0].module, critic.module])
                print(f"warm start: folded constant observation entries {folded}")
            if cfg.get("warm_start_curriculum"):  # rho_j as they were: no reward-scale shock
                base = env.base_env
                env.transform.load_state_dict(adapt_curriculum(init["curriculum"], base.num_worlds, base.num_robots))
        carried = env.reset()
        if cfg.collect.get("desync_episodes"):
            carried = desync_episodes(carried, cfg.env.get("max_episode_steps"))
        if obs_norm is not None and not cfg.warm_start:
            obs_norm.update(carried[OBS])  # first statistics from the initial layouts
    logger = _make_logger(cfg, out_dir, ckpt.get("wandb_id") if ckpt else None)
    wandb_id = getattr(getattr(logger, "experiment", None), "id", None) if cfg.logger.backend == "wandb" else None

    def checkpoint():
        save_checkpoint(ckpt_path, {
            "cfg": OmegaConf.to_container(cfg, resolve=True), "counters": dict(counters),
            "actor": actor.state_dict(), "critic": critic.state_dict(), "optim": optim.state_dict(),
            "curriculum": env.transform.state_dict(), "env": env.base_env.get_state(), "carried": carried,
            "rng": rng_state(), "wandb_id": wandb_id,
            **({"roll_in": roll_in.length.clone()} if roll_in is not None else {}),
        })

    steps = max(1, int(cfg.collect.frames_per_batch) // env.base_env.num_worlds)
    total, every_s = int(cfg.total_iterations), 60.0 * float(cfg.checkpoint_every_min)
    max_wall = math.inf if cfg.max_wall_hours is None else 3600.0 * float(cfg.max_wall_hours)
    wall0, t0 = counters["wall_s"], time.monotonic()
    last_ckpt, row = t0, {}
    bar = tqdm(total=total, initial=counters["iteration"], disable=not cfg.progress, desc="train")
    stop_signal = _StopOnSignal()
    try:
        while counters["iteration"] < total:
            batch, carried = collect(env, actor, carried, steps, roll_in)
            losses = ppo_update(batch, loss, optim, popart, cfg)
            if obs_norm is not None:
                obs_norm.update(batch[OBS])
            counters["iteration"] += 1
            counters["frames"] += batch.numel()
            counters["wall_s"] = wall0 + time.monotonic() - t0
            rho = schedule_of(env).rho_by_term() if hasattr(schedule_of(env), "rho_by_term") else {}
            extra = {"roll_in_frames": float(batch[ROLL_IN].float().mean())} if roll_in is not None else {}
            row = {**counters, **episode_metrics(batch), **losses, **extra, **{f"rho/{k}": v for k, v in rho.items()}}
            with metrics_path.open("a") as f:
                f.write(json.dumps(row) + "\n")
            logger.log_metrics({k: v for k, v in row.items() if math.isfinite(v)}, step=counters["iteration"])
            bar.update(1)
            bar.set_postfix(success=f"{row['success_rate']:.2f}", stage=f"{row['mean_end_stage']:.2f}")
            stop = counters["iteration"] >= total or counters["wall_s"] >= max_wall or stop_signal.received
            if stop or time.monotonic() - last_ckpt >= every_s:
                checkpoint()
                last_ckpt = time.monotonic()
            if stop:
                break
        if not ckpt_path.is_file():  # total already reached at start
            checkpoint()
    finally:
        stop_signal.restore()
    bar.close()
    plot_training(metrics_path, out_dir)
    if cfg.logger.backend == "wandb":
        logger.experiment.finish()
    env.close()
    return {"out_dir": str(out_dir), "checkpoint": str(ckpt_path), "stopped_by_signal": stop_signal.received, **row}


@hydra.main(config_path="config", config_name="train", version_base="1.3")
def main(cfg: DictConfig) -> None:
    if cfg.out_dir is None:
        cfg.out_dir = HydraConfig.get().runtime.output_dir
    train(cfg)


if __name__ == "__main__":
    main()
