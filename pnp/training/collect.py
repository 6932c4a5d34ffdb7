"""Collecting on-policy batches: the step loop, mean roll-ins, desynchronised episode
clocks, and the episode metrics logged per iteration."""
from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase
from tensordict.nn import InteractionType, ProbabilisticTensorDictSequential, set_interaction_type
from torchrl.envs import TransformedEnv

from pnp.task import HL_DT
from pnp.training.device import module_device, policy_step
from pnp.training.models import dist_from_params
from pnp.training.keys import ACTION, EPISODE_STAGE, PEAK, REWARD, ROLL_IN, STAGE, STAGE_ONE_HOT
from pnp.training.recurrent import carry_state, recurrent_net


def seconds(steps) -> float:
    """High-level steps as seconds (10 Hz)."""
    return float(steps) * HL_DT


class MeanRollIn:
    """Episodes that begin with the policy's *mean* action for a random number of steps,
    then sample as usual (a roll-in / roll-out split, as in learning-to-search).

    Why: evaluation runs the mean, and the mean has fixed points that the training noise
    escapes (a MuJoCo policy stood 10 cm short of the handle with its arm at full reach),
    so PPO hardly ever sees those states. Rolled in on the mean, the sampled roll-out
    starts there. Roll-in actions were not drawn from the policy, so their steps are left
    out of the PPO loss; the roll-out's advantages only look ahead.

    ``share`` of episodes get a roll-in of 1..``max_steps`` steps (uniform); the others none.
    """

    def __init__(self, num_worlds: int, share: float, max_steps: int):
        if not 0.0 <= share <= 1.0 or max_steps < 1:
            raise ValueError(f"collect.roll_in_share must be in [0, 1] and collect.roll_in_max_steps >= 1, "
                             f"got {share} and {max_steps}")
        self.share, self.max_steps = share, max_steps
        self.length = torch.zeros(num_worlds, dtype=torch.long)  # roll-in steps of each world's episode

    def begin(self, new: torch.Tensor) -> None:
        """Draw roll-in lengths for the worlds whose episode starts now (bool [N])."""
        n = int(new.sum())
        if n:
            draw = torch.randint(1, self.max_steps + 1, (n,))
            self.length[new] = torch.where(torch.rand(n) < self.share, draw, 0)


def collect(env: TransformedEnv, policy: ProbabilisticTensorDictSequential, carried: TensorDictBase, steps: int,
            roll_in: MeanRollIn | None = None) -> tuple[TensorDictBase, TensorDictBase]:
    """``steps`` steps of every world from ``carried``; returns the [N, T] batch and the next carried td.

    The loop the Collector runs (step_and_maybe_reset), kept here because its carried td
    is the one piece of state a bit-for-bit resume needs and ``Collector.state_dict`` does
    not hold it (its constructor even resets the env). With ``roll_in``, steps inside an
    episode's roll-in take the mean action and are flagged ``ROLL_IN``. The carried td stays
    on the env's device; the batch is returned on the policy's (where the update runs).
    """
    out, recurrent = [], recurrent_net(policy) is not None
    device = module_device(policy)
    # Sampled actions: ProbabilisticActor's default interaction type is deterministic.
    with torch.no_grad(), set_interaction_type(InteractionType.RANDOM):
        for _ in range(steps):
            carried = policy_step(policy, carried, device, env.device)
            if roll_in is not None:
                count = carried["step_count"].reshape(-1)  # steps already taken in the episode
                roll_in.begin(count == 0)
                det = count < roll_in.length
                if det.any():
                    # From the loc/scale the policy just wrote: no second forward.
                    mean = dist_from_params(policy, carried).deterministic_sample
                    carried[ACTION] = torch.where(det[:, None, None], mean, carried[ACTION])
                carried[ROLL_IN] = det.unsqueeze(-1)
            td, carried = env.step_and_maybe_reset(carried)
            out.append(td)
            if recurrent:
                carry_state(td, carried)
    batch = torch.stack(out, -1)
    return (batch if batch.device == device else batch.to(device)), carried  # where the update runs


def desync_episodes(carried: TensorDictBase, max_steps: int | None) -> TensorDictBase:
    """Start each world's first episode at a random step of the ``max_steps`` limit.

    Why: every world resets at once at the start and episodes have a fixed length (no
    termination on success), so without this all worlds stay in phase: each batch of
    T steps holds the same 1-2 s of every episode and consecutive PPO updates see
    different parts of the task (rsl_rl starts episode clocks at random for the same
    reason). Only the first episode of each world is cut short.
    """
    if not max_steps:
        raise ValueError("collect.desync_episodes needs env.max_episode_steps (the limit whose clock it offsets)")
    carried["step_count"] = torch.randint_like(carried["step_count"], 0, int(max_steps))
    return carried


def windowed_mean(rows: list[dict], metric: str, window: int) -> float | None:
    """``metric`` over the last ``window`` rows, weighted by their episode counts (``None``
    before ``window`` rows or when no episode ended in them)."""
    if len(rows) < window:
        return None
    recent = [r for r in rows[-window:] if r.get("episodes", 0) > 0 and math.isfinite(r.get(metric, math.nan))]
    n = sum(r["episodes"] for r in recent)
    return sum(r[metric] * r["episodes"] for r in recent) / n if n else None


def _shares(stages: torch.Tensor, n_stages: int, prefix: str) -> dict[str, float]:
    hist = torch.bincount(stages, minlength=n_stages).float()
    return {f"{prefix}/S{i}": float(h / hist.sum()) if stages.numel() else math.nan for i, h in enumerate(hist)}


def episode_metrics(batch: TensorDictBase) -> dict[str, float]:
    """Success rate, mean end-of-episode stage and stage shares of the episodes that ended."""
    nxt = batch["next"]
    done = nxt["done"].squeeze(-1)
    stage = nxt[EPISODE_STAGE]
    ended = stage[stage >= 0]
    n = int(done.sum())
    out = {"episodes": float(n), "reward": float(nxt[REWARD].mean())}
    out["success_rate"] = float(nxt["success"].squeeze(-1)[done].float().mean()) if n else math.nan
    out["mean_end_stage"] = float(ended.float().mean()) if ended.numel() else math.nan
    won = nxt["success"].squeeze(-1) & done
    # Episodes that go on after success (env.terminate_on_success=false) record its step.
    out["completion_time_s"] = math.nan
    if won.any():
        steps = nxt["success_step"] if "success_step" in nxt.keys() else nxt["step_count"]
        out["completion_time_s"] = seconds(steps.squeeze(-1)[won].float().mean())
    n_stages = nxt[STAGE_ONE_HOT].shape[-1]
    out.update(_shares(ended, n_stages, "stage_share"))
    if nxt.get(PEAK, None) is not None:
        # lambda(e) is the peak stage (curriculum.episode_stage=peak): log the final stage too.
        final = nxt[STAGE][stage >= 0]
        out["mean_final_stage"] = float(final.float().mean()) if final.numel() else math.nan
        out.update(_shares(final, n_stages, "final_stage_share"))
    else:  # lambda(e) is the final stage: the same figure, under the name both modes log
        out["mean_final_stage"] = out["mean_end_stage"]
    return out
