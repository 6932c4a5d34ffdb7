"""A tiny env's models and a 5-step batch collected by their own actor (kinematic, 4 worlds)."""
from __future__ import annotations

import torch

from pnp.training.collect import collect
from pnp.training.models import make_models
from pnp.training.tasks import make_env
from tests.training._tiny import TINY, compose_cfg


def tiny_models_and_batch(steps: int = 5):
    torch.manual_seed(0)
    cfg = compose_cfg("train", TINY)
    env = make_env(cfg.env, cfg.curriculum, 0)
    models = make_models(cfg.model, cfg.loss, env)
    batch, _ = collect(env, models.actor, env.reset(), steps)
    return cfg, models, batch
