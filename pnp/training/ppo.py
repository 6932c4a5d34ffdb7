"""One PPO update of a collected batch, and the KL-adaptive learning rate."""
from __future__ import annotations

import math
from collections import defaultdict

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase

from pnp.losses.mappo import PopArtMAPPOLoss
from pnp.training.keys import ROLL_IN, STAGE_ONE_HOT
from pnp.training.models import GripperFloor
from pnp.training.recurrent import recurrent_net

LOGGED = ("loss_objective", "loss_critic", "loss_entropy", "loss_distill", "loss_grasp_floor", "entropy",
          "explained_variance", "clip_fraction", "kl_approx", "kl", "kl_gripper", "kl_teacher", "loss_stage",
          "stage_accuracy")


def adapt_lr(optim: torch.optim.Optimizer, kl: float, ocfg: DictConfig) -> None:
    """KL-adaptive step size (as rsl_rl): divide by 1.5 when the KL exceeds twice the
    target, multiply by 1.5 when it is below half, within [min_lr, max_lr]. A fixed lr is
    too large or too small as the policy sharpens."""
    if ocfg.lr_schedule == "fixed":
        return
    if ocfg.lr_schedule != "adaptive":
        raise ValueError(f"optim.lr_schedule must be 'adaptive' or 'fixed', got {ocfg.lr_schedule!r}")
    for g in optim.param_groups:
        if kl > 2.0 * ocfg.desired_kl:
            g["lr"] = max(g["lr"] / 1.5, float(ocfg.min_lr))
        elif kl < 0.5 * ocfg.desired_kl:
            g["lr"] = min(g["lr"] * 1.5, float(ocfg.max_lr))


def minibatch_source(batch: TensorDictBase, recurrent: bool, cfg: DictConfig) -> TensorDictBase:
    """What minibatches are drawn from: frames ``[N * T]``, or for a recurrent actor whole
    segments ``[N, T]`` (one world's steps of this batch, in order: its GRU runs over them)."""
    if recurrent:
        if ROLL_IN in batch.keys():
            raise ValueError(f"collect.roll_in_share={cfg.collect.roll_in_share}: roll-ins are dropped frame by "
                             "frame, which a recurrent student's segments cannot lose; set it to 0")
        return batch
    flat = batch.reshape(-1)
    if ROLL_IN in flat.keys():  # roll-in actions were the mean, not drawn: no policy gradient from them
        flat = flat[~flat[ROLL_IN].reshape(-1)]
    return flat


def ppo_update(batch: TensorDictBase, loss: PopArtMAPPOLoss, optim: torch.optim.Optimizer,
               cfg: DictConfig) -> dict[str, float]:
    """GAE once per iteration, PopArt statistics once, then epochs of shuffled minibatches;
    returns the means of the logged loss entries (``train/...``)."""
    with torch.no_grad():
        loss.value_estimator(batch)
    loss.update_value_norm(batch)
    memory = recurrent_net(loss.actor_network)
    flat = minibatch_source(batch, memory is not None, cfg)
    params = [p for g in optim.param_groups for p in g["params"]]
    floors = [m for m in loss.actor_network.modules() if isinstance(m, GripperFloor) and m.coeff > 0]
    sums, n, skipped = defaultdict(float), 0, []
    rows = flat.batch_size[0]  # not numel(): a TensorDict of batch [0] reports 1
    per_minibatch = max(1, int(cfg.collect.minibatch_size) // math.prod(flat.batch_size[1:]))  # rows of T steps
    for _ in range(int(cfg.collect.num_epochs) if rows else 0):
        for idx in torch.randperm(rows).split(per_minibatch):
            minibatch = flat[idx]
            out = loss(minibatch)
            for f in floors:  # from the actor forward the loss just made
                out.set("loss_grasp_floor", f.penalty())
            if memory is not None and memory.stage_head is not None:  # likewise
                loss_stage, accuracy = memory.stage_loss(minibatch.get(STAGE_ONE_HOT))
                out.set("loss_stage", loss_stage)
                out.set("stage_accuracy", accuracy)
            adapt_lr(optim, float(out["kl"]), cfg.optim)  # the lr of this very step
            total = sum(v for k, v in out.items() if k.startswith("loss_"))  # MAPPO's, and any a subclass adds
            optim.zero_grad(set_to_none=True)
            total.backward()
            grads = [q.grad for q in params if q.grad is not None]
            norm = torch.nn.utils.get_total_norm(grads)  # as clip_grad_norm_ computes it
            if not bool(torch.isfinite(norm)):
                # Clipping by a non-finite norm turns every gradient into NaN: one saturated
                # log-probability would poison all parameters. The step is skipped instead,
                # and the parameters named while their gradients still show where it came from.
                skipped.append(_nonfinite_grads(loss))
                continue
            torch.nn.utils.clip_grads_with_norm_(params, float(cfg.optim.max_grad_norm), norm)
            optim.step()
            sums["grad_norm"] += float(norm)
            for k in LOGGED:
                if k in out.keys():
                    sums[k] += float(out[k].detach().float().mean())
            n += 1
    if skipped and n == 0:
        raise FloatingPointError(f"every one of this iteration's {len(skipped)} PPO steps had a non-finite gradient "
                                 f"(first in {skipped[0][:4]}): the parameters are kept as they were; the run diverges")
    # n == 0 (every frame a roll-in) leaves no sums to divide.
    return {**{f"train/{k}": v / n for k, v in sums.items()}, "train/lr": optim.param_groups[0]["lr"],
            "train/skipped_steps": len(skipped)}


def _nonfinite_grads(loss: torch.nn.Module) -> list[str]:
    """Names of the parameters whose gradient holds inf or NaN."""
    return [name for name, p in loss.named_parameters() if p.grad is not None and not bool(torch.isfinite(p.grad).all())]
