"""Tasks the trainer knows: each a stage graph, a reward configuration and an env, wrapped
as StepCounter -> StageTransition -> reward schedule."""
from __future__ import annotations

import math
from typing import Callable

from omegaconf import DictConfig, OmegaConf
from torchrl.envs import Compose, EnvBase, RewardClipping, StepCounter, TransformedEnv

from pnp.sim.box import DUAL_ROBOT_BOXES, SINGLE_ROBOT_BOXES
from pnp.task.ee_tracking import ee_reward_config, ee_stage_graph
from pnp.envs.ee_tracking_env import EETrackingEnv
from pnp.envs.locomotion_env import LocomotionEnv
from pnp.envs.pnp_env import PnPEnv
from pnp.legs.locomotion import locomotion_reward_config, locomotion_stage_graph
from pnp.task.stage_graph import StageGraph, pnp_default_reward_config, pnp_default_stage_graph
from pnp.training.config import EETrackingConfig, EnvConfig, KinematicOptions
from pnp.training.keys import REWARD, STAGE_ONE_HOT
from pnp.training.low_level import LOW_LEVELS, learned_backend
from pnp.transforms import StageRewardSchedule, StageTransition, make_reward_schedule

BACKENDS = ("mujoco", "kinematic")
BOX_SETS = {None: None, "single": SINGLE_ROBOT_BOXES, "dual": DUAL_ROBOT_BOXES}


def _pnp_env(env_cfg: DictConfig, seed: int) -> EnvBase:
    if env_cfg.boxes not in BOX_SETS:
        raise ValueError(f"env.boxes must be null, 'single' or 'dual', got {env_cfg.boxes!r}")
    if env_cfg.low_level not in LOW_LEVELS:
        raise ValueError(f"env.low_level must be one of {LOW_LEVELS}, got {env_cfg.low_level!r}")
    backend, options = env_cfg.backend, kinematic_options(env_cfg)
    if env_cfg.finger_speed is not None:
        if env_cfg.backend != "mujoco":
            raise ValueError(f"env.finger_speed={env_cfg.finger_speed} applies to MuJoCo's fingers; the kinematic "
                             "backend's move at pnp.kinematic.step.FINGER_SPEED")
        options = {"finger_speed": float(env_cfg.finger_speed)}
    if env_cfg.low_level == "learned":
        backend = learned_backend(env_cfg, BOX_SETS[env_cfg.boxes])
    return PnPEnv(num_worlds=int(env_cfg.num_worlds), num_robots=int(env_cfg.num_robots), backend=backend,
                  backend_options=options, seed=int(seed), nthread=env_cfg.nthread,
                  start_range=tuple(env_cfg.start_range),
                  terminate_on_success=bool(env_cfg.terminate_on_success), handle_order=env_cfg.handle_order,
                  handle_claim=bool(env_cfg.handle_claim), box_assets=BOX_SETS[env_cfg.boxes],
                  paired_trials=bool(env_cfg.paired_trials),
                  box_mass=None if env_cfg.box_mass is None else tuple(env_cfg.box_mass),
                  action_bounds={k: list(v) for k, v in env_cfg.action_bounds.items()},
                  grasp_pose=str(env_cfg.grasp_pose))


def _ee_tracking_env(env_cfg: DictConfig, seed: int) -> EnvBase:
    if int(env_cfg.num_robots) != 1:
        raise ValueError(f"env.task=ee_tracking has one robot, got env.num_robots={env_cfg.num_robots}")
    kinematic_options(env_cfg)  # refuses kinematic options on MuJoCo here too
    _ideal_only(env_cfg)
    _pnp_only_options(env_cfg)
    task = env_cfg.ee_tracking
    return EETrackingEnv(num_worlds=int(env_cfg.num_worlds), backend=env_cfg.backend, seed=int(seed),
                         nthread=env_cfg.nthread, track_rule=str(task.track_rule), track_sigma=tuple(task.track_sigma),
                         point_ring=tuple(task.point_ring), terminate_on_success=bool(env_cfg.terminate_on_success))


def _pnp_only_options(env_cfg: DictConfig) -> None:
    if env_cfg.action_bounds:
        raise ValueError(f"env.action_bounds={dict(env_cfg.action_bounds)} narrows the pick-and-place action; "
                         f"env.task={env_cfg.task} has its own")
    if env_cfg.grasp_pose != EnvConfig.grasp_pose:  # the schema's default: Table II as we read it
        raise ValueError(f"env.grasp_pose={env_cfg.grasp_pose!r} is a pick-and-place reward term; "
                         f"env.task={env_cfg.task} has its own")


def _locomotion_env(env_cfg: DictConfig, seed: int) -> EnvBase:
    _pnp_only_options(env_cfg)
    if env_cfg.backend != "mujoco":
        raise ValueError(f"env.task=locomotion simulates legs: it needs env.backend=mujoco, got {env_cfg.backend!r}")
    if int(env_cfg.num_robots) != 1:
        raise ValueError(f"env.task=locomotion has one robot, got env.num_robots={env_cfg.num_robots}")
    kinematic_options(env_cfg)
    _ideal_only(env_cfg)
    steps = env_cfg.max_episode_steps
    return LocomotionEnv(num_worlds=int(env_cfg.num_worlds), settings=env_cfg.locomotion, seed=int(seed),
                         nthread=env_cfg.nthread, **({} if steps is None else {"max_episode_steps": int(steps)}))


# env.task -> (stage graph, reward-schedule kwargs, env): what the trainer needs of a task.
TASKS: dict[str, tuple[Callable[[], StageGraph], Callable[[], dict], Callable[[DictConfig, int], EnvBase]]] = {
    "pnp": (pnp_default_stage_graph, pnp_default_reward_config, _pnp_env),
    "ee_tracking": (ee_stage_graph, ee_reward_config, _ee_tracking_env),
    "locomotion": (locomotion_stage_graph, locomotion_reward_config, _locomotion_env),
}


def kinematic_options(env_cfg: DictConfig) -> dict | None:
    """``env.kinematic`` as backend options; a MuJoCo run refuses any that is switched on
    (they stand in for contacts MuJoCo simulates)."""
    if env_cfg.backend not in BACKENDS:
        raise ValueError(f"env.backend must be one of {BACKENDS}, got {env_cfg.backend!r}")
    opts = {k: v for k, v in dict(env_cfg.kinematic or {}).items() if v != getattr(KinematicOptions, k)}
    if env_cfg.backend != "kinematic":
        if opts:
            raise ValueError(f"env.kinematic options {sorted(opts)} apply to the kinematic backend only; this run "
                             f"uses env.backend={env_cfg.backend!r} (leave them at their defaults)")
        return None
    return opts or None


def _ideal_only(env_cfg: DictConfig) -> None:
    if env_cfg.low_level != "ideal":
        raise ValueError(f"env.low_level={env_cfg.low_level!r} applies to env.task=pnp only, not {env_cfg.task!r}")


def _task(env_cfg: DictConfig) -> tuple:
    if env_cfg.task not in TASKS:
        raise ValueError(f"env.task must be one of {sorted(TASKS)}, got {env_cfg.task!r}")
    own = OmegaConf.to_container(env_cfg.ee_tracking)
    if env_cfg.task != "ee_tracking" and own != OmegaConf.to_container(OmegaConf.structured(EETrackingConfig)):
        raise ValueError(f"env.ee_tracking={own} sets the EE-tracking task; this run's env.task is {env_cfg.task!r}")
    return TASKS[env_cfg.task]


def schedule_args(cur: DictConfig, task: str = "pnp") -> tuple[str, dict]:
    """Name and kwargs of ``make_reward_schedule`` for a ``curriculum`` config."""
    cfg = TASKS[task][1]()
    over = dict(cur.fixed_weights or {})
    unknown = sorted(set(over) - set(cfg["fixed_weights"]))
    if unknown:
        raise ValueError(f"curriculum.fixed_weights names unknown terms {unknown}; the R_fixed terms of "
                         f"{task!r} are {sorted(cfg['fixed_weights'])}")
    cfg["fixed_weights"].update({k: float(v) for k, v in over.items()})
    gates = {k: int(v) for k, v in (cur.stage_gates or {}).items()}
    bad = sorted(k for k, v in gates.items() if k not in cfg["mu"] or not 0 <= v < cfg["n_stages"])
    if bad:
        raise ValueError(f"curriculum.stage_gates: {({k: gates[k] for k in bad})} names no stage-wise term of {task!r} "
                         f"({sorted(cfg['mu'])}) or no stage in [0, {cfg['n_stages']})")
    cfg["stage_gates"] = {**cfg.get("stage_gates", {}), **gates}
    if not cur.stage_rewards:
        # Control run: only R_fixed; every stage-wise term becomes a fixed term of weight 0.
        cfg["fixed_weights"].update({n: 0.0 for n in cfg["mu"]})
        cfg.update(term_stage={}, mu={})
        return "fixed", cfg
    cfg.update(K=float(cur.K), mu_min=float(cur.mu_min), final_after=int(cur.final_after),
               completed_floor=float(cur.completed_floor))
    return str(cur.schedule), cfg


def stage_graph(cur_cfg: DictConfig, task: str = "pnp") -> StageGraph:
    """The task's stage graph, with ``curriculum.backward_edges`` (a list of [from, to]
    stage names or indices) in place of its own backward edges when that is set."""
    graph = TASKS[task][0]()
    if cur_cfg.backward_edges is None:
        return graph
    pairs = [tuple(e) for e in cur_cfg.backward_edges]
    bad = [e for e in pairs if len(e) != 2]
    if bad:
        raise ValueError(f"curriculum.backward_edges needs [from, to] pairs, got {bad}")
    return StageGraph(graph.stages, graph.conditions, tuple(pairs))


def make_env(env_cfg: DictConfig, cur_cfg: DictConfig, seed: int) -> TransformedEnv:
    """The ``env.task`` env wrapped in StepCounter -> StageTransition -> reward schedule
    (-> RewardClipping at 0 for a locomotion env with ``only_positive_rewards``)."""
    make_base = _task(env_cfg)[2]
    name, sched = schedule_args(cur_cfg, env_cfg.task)
    transforms = [
        # Before StageTransition: a shorter episode limit sets done, which ends the stage.
        StepCounter(max_steps=env_cfg.max_episode_steps),
        StageTransition(stage_graph(cur_cfg, env_cfg.task), one_hot_key=STAGE_ONE_HOT,
                        episode_stage=str(cur_cfg.episode_stage)),
        make_reward_schedule(name, **sched),
    ]
    if env_cfg.task == "locomotion" and env_cfg.locomotion.only_positive_rewards:
        transforms.append(RewardClipping(0.0, math.inf, in_keys=[REWARD]))
    return TransformedEnv(make_base(env_cfg, seed), Compose(*transforms))


def schedule_of(env: TransformedEnv) -> StageRewardSchedule:
    return next(t for t in env.transform if isinstance(t, StageRewardSchedule))
