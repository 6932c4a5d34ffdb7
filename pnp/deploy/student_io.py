"""A student checkpoint loaded the way a deployment needs it: its configuration, its env
(one evaluation world unless asked) and its actor, as ``pnp.distill.student`` builds them."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from omegaconf import DictConfig
from torchrl.envs import TransformedEnv

from pnp.distill.config import distill_config
from pnp.distill.student import load_student_actor, make_student_env
from pnp.training.checkpoint import load_checkpoint, seed_everything
from pnp.training.rollout import evaluation_env_config


@dataclass
class LoadedStudent:
    cfg: DictConfig
    ckpt: dict
    env: TransformedEnv
    actor: object


def student_env(path: str | Path, num_worlds: int = 1, seed: int = 0, view: str = "student",
                **env_overrides) -> tuple[DictConfig, dict, TransformedEnv]:
    """The student of checkpoint ``path``: its configuration, checkpoint and an evaluation env of
    ``num_worlds`` worlds (paper layouts, seeded by ``seed``; ``env_overrides`` as
    ``recipes/evaluate_student.py``'s env.*) with the observation transforms of ``view``
    (``pnp.distill.student.VIEWS``; ``clean``: none, the deployment's world)."""
    ckpt = load_checkpoint(Path(path))
    if "distill" not in ckpt["cfg"]:
        raise ValueError(f"{path} is a teacher's checkpoint (no distill section): deployment runs a student")
    cfg = distill_config(ckpt["cfg"])
    evaluation_env_config(cfg.env, num_worlds, **env_overrides)
    seed_everything(seed)
    return cfg, ckpt, make_student_env(cfg, seed, view)


def load_student(path: str | Path, num_worlds: int = 1, seed: int = 0, **env_overrides) -> LoadedStudent:
    """:func:`student_env` with the student's observation and its actor."""
    cfg, ckpt, env = student_env(path, num_worlds, seed, "student", **env_overrides)
    return LoadedStudent(cfg, ckpt, env, load_student_actor(cfg, env, ckpt))
