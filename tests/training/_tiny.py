"""A tiny training configuration (kinematic backend, 4 worlds) and helpers to compose it."""
from __future__ import annotations

from pathlib import Path

from hydra import compose, initialize_config_dir

from pnp.training.config import register
from pnp.training.trainer import train

ROOT = Path(__file__).resolve().parents[2]
CONFIG_DIR = str(ROOT / "recipes" / "config")
TINY = [
    "backend=kinematic", "env.num_worlds=4", "env.max_episode_steps=6", "collect.frames_per_batch=40",
    "collect.minibatch_size=20", "collect.num_epochs=2", "model.actor_cells=[32,32]", "model.critic_cells=[32,32]",
    "logger.backend=csv", "progress=false",
]
register()


def compose_cfg(name: str, overrides: list[str]):
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        return compose(name, overrides=overrides)


def tiny_train(out_dir: Path, *extra: str) -> dict:
    return train(compose_cfg("train", [*TINY, f"out_dir={out_dir}", *extra]))
