"""The parts of some runs, not of every run, as hooks on the runner (:class:`~pnp.training.trainer.Trainer`).

A hook is called around each iteration and may keep state, which the checkpoint stores
under its ``key`` and a resume restores. The runner's own loop (collect, PPO update, log,
checkpoint) knows no method: mean roll-ins (:class:`RollIns`), Bendikas et al.'s sub-tasks
(``pnp.baselines.bendikas.SubtaskHook``) and the distillation's teacher labels and KL weight
(``pnp.distill.trainer``) are hooks.
"""
from __future__ import annotations

from tensordict import TensorDictBase

from pnp.training.collect import MeanRollIn
from pnp.training.keys import ROLL_IN


class RunHook:
    """Does nothing; subclasses override what they need. ``key``: the checkpoint entry of
    :meth:`state_dict` (None: the hook keeps no state)."""

    key: str | None = None

    def on_warm_start(self, runner, init: dict) -> None:
        """A fresh run starts from ``init`` (another run's checkpoint)."""

    def on_ready(self, runner) -> None:
        """The run is built, started or restored, before its first iteration."""

    def before_collect(self, runner) -> None:
        """An iteration begins."""

    def on_batch(self, runner, batch: TensorDictBase) -> None:
        """The batch is collected, before the update."""

    def on_row(self, runner, batch: TensorDictBase, row: dict) -> dict:
        """The update is done; returns entries for the iteration's metrics row."""
        return {}

    def state_dict(self):
        return None

    def load_state_dict(self, state) -> None:
        pass


class RollIns(RunHook):
    """Episodes that begin on the policy's mean action (``collect.roll_in_share``); collection
    reads :attr:`roll_in`, this hook keeps its per-world lengths and logs the roll-in share."""

    key = "roll_in"

    def __init__(self, num_worlds: int, share: float, max_steps: int):
        self.roll_in = MeanRollIn(num_worlds, share, max_steps)

    def on_row(self, runner, batch: TensorDictBase, row: dict) -> dict:
        return {"roll_in_frames": float(batch[ROLL_IN].float().mean())}

    def state_dict(self):
        return self.roll_in.length.clone()

    def load_state_dict(self, state) -> None:
        self.roll_in.length.copy_(state)
