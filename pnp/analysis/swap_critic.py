"""A diagnostic checkpoint: one run's actor with another run's critic, to ask which of the two
a difference in learning lives in (docs/history/pipeline_single/run_17.md).

    python recipes/analyze/swap_critic.py actor_from=runs/main17/4_mujoco/checkpoint.pt \
        critic_from=runs/chain/mj_ft5_1861.pt out=runs/chain/main17_mujoco_chaincritic.pt

Everything but the critic comes from ``actor_from`` (the observation statistics, which actor
and critic share, included). The critic's first layer is re-expressed for those statistics, so
it computes what it computed under its own (exactly, inside both normalisers' +-5 clip). The
optimiser's moments stay ``actor_from``'s: Adam's first moment forgets them within ~10 steps.
"""
from __future__ import annotations

import torch

from pnp.analysis.analysis_cli import settings
from pnp.training.models import ObsNorm

_NORM, _W, _B = "module.obs_norm.", "module.mlp.params.0.weight", "module.mlp.params.0.bias"
DEFAULTS = {"actor_from": None, "critic_from": None, "out": None}


def _std(sd: dict) -> torch.Tensor:
    """The normaliser's divisor, as the network computes it."""
    norm = ObsNorm(len(sd[_NORM + "mean"]))
    norm.load_state_dict({k: sd[_NORM + k] for k in ("mean", "var", "count")})
    return norm.std().double()


def reexpress_critic(critic: dict, stats_from: dict) -> dict:
    """``critic``'s state dict with ``stats_from``'s observation statistics and a first layer
    that maps them to the same pre-activations: W_b (x - m_b) / s_b = W' (x - m_a) / s_a + c."""
    out = {k: v.clone() for k, v in critic.items()}
    ma, mb = stats_from[_NORM + "mean"].double(), critic[_NORM + "mean"].double()
    sa, sb = _std(stats_from), _std(critic)
    w, b = critic[_W].double(), critic[_B].double()
    n = len(ma)  # the stage one-hot after the observation is not normalised
    out[_B] = (b + w[..., :n] @ ((ma - mb) / sb)).to(critic[_B].dtype)
    w = w.clone()
    w[..., :n] = w[..., :n] * (sa / sb)
    out[_W] = w.to(critic[_W].dtype)
    for k in ("mean", "var", "count"):
        out[_NORM + k] = stats_from[_NORM + k].clone()
    return out


def main(argv: list[str]) -> dict:
    cfg = settings(argv, DEFAULTS, __doc__, required=tuple(DEFAULTS))
    a = torch.load(cfg.actor_from, weights_only=False, map_location="cpu")
    b = torch.load(cfg.critic_from, weights_only=False, map_location="cpu")
    for name, ckpt in (("actor_from", a), ("critic_from", b)):
        if not all(k in ckpt.get("critic", {}) for k in (_W, _B, _NORM + "var")):
            raise ValueError(f"{name}={getattr(cfg, name)!r} has no single-network critic with observation statistics")
    if a["critic"][_W].shape != b["critic"][_W].shape:
        raise ValueError(f"critic shapes differ: {tuple(a['critic'][_W].shape)} in actor_from, "
                         f"{tuple(b['critic'][_W].shape)} in critic_from")
    a["critic"] = reexpress_critic(b["critic"], a["critic"])
    a["critic_from"] = str(cfg.critic_from)
    torch.save(a, cfg.out)
    print(f"{cfg.out}: actor and statistics from {cfg.actor_from}, critic from {cfg.critic_from}")
    return a
