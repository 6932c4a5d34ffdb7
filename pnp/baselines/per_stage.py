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
from torchrl.envs import Transform, TransformedEnv

from pnp.losses.erskine import CooperativeMAPPOLoss
from pnp.losses.mappo import PopArtMAPPOLoss
from pnp.baselines.bendikas import SequentialSchedule
from pnp.training.hooks import RunHook
from pnp.training.tasks import schedule_args, schedule_of
from pnp.transforms.baselines import SequentialSubtask, StageRewards

# The StageRewardSchedule arguments among the task's reward configuration.
_SCHEDULE_KEYS = ("term_names", "term_stage", "mu", "fixed_weights", "n_stages", "stage_progress_term", "stage_gates")


class PerStageMethod:
    """A per-stage baseline in our trainer (one subclass per method, its settings in
    ``baseline.<name>``, registered in :data:`METHODS` under its ``model.per_stage`` name):
    the reward schedule that replaces ours, the loss, and the hooks it adds to the runner.
    Its per-stage actor and critic ensembles are built by ``pnp.training.models.make_models``."""

    name: str

    def schedule(self, cfg: DictConfig, high, base: dict) -> Transform:
        raise NotImplementedError

    def loss(self, cfg: DictConfig) -> tuple[type[PopArtMAPPOLoss], dict]:
        return PopArtMAPPOLoss, {}

    def hooks(self, cfg: DictConfig, runner) -> list[RunHook]:
        return []


class Bendikas(PerStageMethod):
    """One sub-task at a time, each policy starting from the last (``baseline.bendikas``)."""

    name = "bendikas"

    def schedule(self, cfg: DictConfig, high, base: dict) -> Transform:
        return SequentialSubtask(high=high, gamma=float(cfg.loss.gamma),
                                 success_bonus=float(cfg.baseline.bendikas.success_bonus), **base)

    def hooks(self, cfg: DictConfig, runner) -> list[RunHook]:
        m = runner.models
        return [SequentialSchedule(cfg.baseline.bendikas, schedule_of(runner.env), m.actor_net, m.critic_net,
                                   runner.optim)]


class Erskine(PerStageMethod):
    """Every stage's critic, the advantages of a stage and the next mixed (``baseline.erskine``)."""

    name = "erskine"

    def schedule(self, cfg: DictConfig, high, base: dict) -> Transform:
        return StageRewards(high=high, completed_share=float(cfg.baseline.erskine.completed_share), **base)

    def loss(self, cfg: DictConfig) -> tuple[type[PopArtMAPPOLoss], dict]:
        return CooperativeMAPPOLoss, {"mix": float(cfg.baseline.erskine.mix)}


METHODS: dict[str, PerStageMethod] = {m.name: m for m in (Bendikas(), Erskine())}


def method_of(cfg: DictConfig) -> PerStageMethod | None:
    """The baseline ``model.per_stage`` names; None for ours ("none")."""
    name = cfg.model.per_stage
    if name == "none":
        return None
    if name not in METHODS:
        raise ValueError(f"model.per_stage must be 'none' or one of {sorted(METHODS)}, got {name!r}")
    return METHODS[name]


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
    method = method_of(cfg)
    if method is None:
        return
    _check(cfg)
    _, kwargs = schedule_args(cfg.curriculum, cfg.env.task)
    schedule = method.schedule(cfg, kwargs["high"], {k: kwargs[k] for k in _SCHEDULE_KEYS})
    env.transform.pop()
    env.append_transform(schedule)


def method_hooks(cfg: DictConfig, runner) -> list[RunHook]:
    """What the method adds to the runner's loop (Bendikas' sub-task schedule)."""
    method = method_of(cfg)
    return method.hooks(cfg, runner) if method is not None else []


def baseline_loss(cfg: DictConfig) -> tuple[type[PopArtMAPPOLoss], dict]:
    """The loss class and its extra arguments (for ``trainer.make_loss``)."""
    method = method_of(cfg)
    return method.loss(cfg) if method is not None else (PopArtMAPPOLoss, {})
