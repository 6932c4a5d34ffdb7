"""The per-stage baselines in our trainer: Bendikas et al. and Erskine et al.

Both keep the env, low-level executor, network size per policy and PPO settings of ours,
and the fixed scales mu_j plus R_fixed (``curriculum.schedule=fixed``). What differs,
chosen by ``model.per_stage``:

* ``bendikas``: the reward schedule is the current sub-task's
  (``pnp.transforms.baselines.SequentialSubtask``), the loss is our MAPPO loss, and
  ``pnp.baselines.bendikas.SequentialSchedule`` moves the sub-task on.
* ``erskine``: the schedule also writes each stage's reward
  (``pnp.transforms.baselines.StageRewards``) and the loss mixes the stage critics'
  advantages (``pnp.losses.erskine.CooperativeMAPPOLoss``).

The originals were off-policy actor-critics (Bendikas et al. transferred replay buffers
between sub-tasks; Erskine et al. built on soft actor-critic); these are our PPO readings.
"""
from __future__ import annotations

from omegaconf import DictConfig
from torchrl.envs import TransformedEnv

from pnp.losses.erskine import CooperativeMAPPOLoss
from pnp.losses.mappo import PopArtMAPPOLoss
from pnp.baselines.bendikas import SequentialSchedule
from pnp.training.hooks import RunHook
from pnp.training.tasks import schedule_args, schedule_of
from pnp.transforms.baselines import SequentialSubtask, StageRewards

# The StageRewardSchedule arguments among the task's reward configuration.
_SCHEDULE_KEYS = ("term_names", "term_stage", "mu", "fixed_weights", "n_stages", "stage_progress_term", "stage_gates")


def is_baseline(cfg: DictConfig) -> bool:
    return cfg.model.per_stage != "none"


def _check(cfg: DictConfig) -> None:
    cur = cfg.curriculum
    if cur.schedule != "fixed" or not cur.stage_rewards:
        raise ValueError(f"model.per_stage={cfg.model.per_stage!r} trains on the fixed scales mu_j: it needs "
                         f"curriculum.schedule=fixed and curriculum.stage_rewards=true, got {cur.schedule!r} and "
                         f"{cur.stage_rewards}")
    if cfg.env.task != "pnp":
        raise ValueError(f"model.per_stage={cfg.model.per_stage!r} is for env.task=pnp, got {cfg.env.task!r}")


def use_baseline_schedule(env: TransformedEnv, cfg: DictConfig) -> None:
    """Replace ``env``'s reward schedule (last in its Compose) by the baseline's; nothing
    for ours. The baseline's is a FixedScales subclass built from the same arguments."""
    if not is_baseline(cfg):
        return
    _check(cfg)
    _, kwargs = schedule_args(cfg.curriculum, cfg.env.task)
    base = {k: kwargs[k] for k in _SCHEDULE_KEYS}
    if cfg.model.per_stage == "bendikas":
        schedule = SequentialSubtask(high=kwargs["high"], gamma=float(cfg.loss.gamma),
                                     success_bonus=float(cfg.baseline.bendikas.success_bonus), **base)
    else:
        schedule = StageRewards(high=kwargs["high"], completed_share=float(cfg.baseline.erskine.completed_share), **base)
    env.transform.pop()
    env.append_transform(schedule)


def method_hooks(cfg: DictConfig, runner) -> list[RunHook]:
    """What the method adds to the runner's loop: Bendikas' sub-task schedule; nothing else."""
    if cfg.model.per_stage != "bendikas":
        return []
    m = runner.models
    return [SequentialSchedule(cfg.baseline.bendikas, schedule_of(runner.env), m.actor_net, m.critic_net, runner.optim)]


def baseline_loss(cfg: DictConfig) -> tuple[type[PopArtMAPPOLoss], dict]:
    """The loss class and its extra arguments (for ``trainer.make_loss``)."""
    if cfg.model.per_stage == "erskine":
        return CooperativeMAPPOLoss, {"mix": float(cfg.baseline.erskine.mix)}
    return PopArtMAPPOLoss, {}
