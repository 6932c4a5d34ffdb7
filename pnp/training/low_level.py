"""The learned low level in a pick-and-place env (``env.low_level=learned``): a locomotion
policy from a ``task=locomotion`` checkpoint, driving the legs of ``pnp.legs.backend``."""
from __future__ import annotations

from dataclasses import dataclass

import torch
from omegaconf import DictConfig
from tensordict import TensorDict
from tensordict.nn import InteractionType, set_interaction_type

from pnp.sim.box import BoxAsset, DUAL_ROBOT_BOXES, SINGLE_ROBOT_BOXES
from pnp.legs.backend import LeggedMujocoBackend, LowLevelPolicy
from pnp.envs.locomotion_env import leg_action_spec
from pnp.legs.locomotion import LOCO_OBS_DIM, LegServo
from pnp.training.checkpoint import load_checkpoint, resolve_checkpoint
from pnp.training.migration import migrate
from pnp.training.keys import ACTION, OBS, STAGE_ONE_HOT

LOW_LEVELS = ("ideal", "learned")


@dataclass(frozen=True)
class LocomotionPolicy:
    """A leg policy (observations [M, LOCO_OBS_DIM] -> leg actions [M, 12]) and the servos it was trained under."""

    act: LowLevelPolicy
    servo: LegServo

    def __call__(self, obs: torch.Tensor) -> torch.Tensor:
        return self.act(obs)


def load_locomotion_policy(checkpoint: str) -> LocomotionPolicy:
    """The deterministic leg policy of a ``task=locomotion`` run folder or checkpoint file:
    observations [M, LOCO_OBS_DIM] (raw; the checkpoint's normalisation applies) -> leg actions
    [M, 12], with the servo gains and action scale of its training (``env.locomotion``)."""
    from pnp.training.models import PolicySpecs, make_models  # the trainer's stack, loaded only when asked for

    path = resolve_checkpoint(checkpoint, "runs")
    ckpt = load_checkpoint(path)
    cfg = migrate(ckpt["cfg"])
    if cfg.env.task != "locomotion":
        raise ValueError(f"env.low_level_checkpoint {path} was trained on env.task={cfg.env.task!r}, not locomotion")
    specs = PolicySpecs(n_agents=1, n_obs=LOCO_OBS_DIM, n_stages=1, action=leg_action_spec())  # the task's one stage
    actor = make_models(cfg.model, cfg.loss, specs).actor
    actor.load_state_dict(ckpt["actor"])
    actor.eval()

    @torch.no_grad()
    def policy(obs: torch.Tensor) -> torch.Tensor:
        if obs.ndim != 2 or obs.shape[-1] != LOCO_OBS_DIM:
            raise ValueError(f"locomotion observations must be [M, {LOCO_OBS_DIM}], got {tuple(obs.shape)}")
        m = obs.shape[0]
        td = TensorDict(batch_size=[m])
        td.set(OBS, obs.unsqueeze(1))
        td.set(STAGE_ONE_HOT, torch.ones(m, 1, 1))  # the locomotion task's single stage
        with set_interaction_type(InteractionType.DETERMINISTIC):
            return actor(td).get(ACTION)[:, 0]

    loco = cfg.env.locomotion
    return LocomotionPolicy(policy, LegServo(float(loco.leg_kp), float(loco.leg_kd), float(loco.action_scale)))


def learned_backend(env_cfg: DictConfig, boxes: tuple[BoxAsset, ...] | None) -> LeggedMujocoBackend:
    """The legged MuJoCo backend of ``env_cfg`` (``low_level=learned``), its legs walked by
    ``env_cfg.low_level_checkpoint``'s policy."""
    if env_cfg.backend != "mujoco":
        raise ValueError(f"env.low_level=learned walks simulated legs: it needs env.backend=mujoco, got {env_cfg.backend!r}")
    if not env_cfg.low_level_checkpoint:
        raise ValueError("env.low_level=learned needs env.low_level_checkpoint: a task=locomotion run folder or checkpoint")
    robots = int(env_cfg.num_robots)
    boxes = boxes or (SINGLE_ROBOT_BOXES if robots == 1 else DUAL_ROBOT_BOXES)
    policy = load_locomotion_policy(str(env_cfg.low_level_checkpoint))
    return LeggedMujocoBackend(int(env_cfg.num_worlds), robots, boxes[0], policy, nthread=env_cfg.nthread,
                               finger_speed=env_cfg.finger_speed, servo=policy.servo)
