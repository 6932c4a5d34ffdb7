"""Bendikas et al.'s training order: one sub-task at a time, each policy starting from the last.

Sub-task k (``pnp.transforms.baselines.SequentialSubtask``: rewards of stages <= k,
success at S_{k+1}) trains member k of the actor and critic ensembles, which act in every
stage. It ends when its training success rate over the last ``window`` iterations
(weighted by their episodes) reaches ``min_success``, or when it has used ``max_frames``;
then member k+1 becomes a copy of member k (weights and Adam moments: a fresh Adam on a
sharpened policy made KL jumps in our warm starts) and the env moves to sub-task k+1.
The last sub-task is the whole task and trains to the end of the budget; its member is
the policy evaluated.

The sub-task in training is the actor's route table (saved with its weights, so an
evaluation loads the right member); the env and the critic follow it (:meth:`sync`).
"""
from __future__ import annotations

import torch
from omegaconf import DictConfig

from pnp.training.collect import windowed_mean
from pnp.training.hooks import RunHook
from pnp.training.stage_ensemble import StageEnsemble
from pnp.transforms.baselines import SequentialSubtask

EXITS = {"success": 1, "frames": 2}  # logged as subtask_exit (0: the sub-task goes on)


def check_sequential(cfg: DictConfig) -> None:
    """Refuse settings that cannot work, naming them (``baseline.bendikas``)."""
    if not 0.0 < float(cfg.min_success) <= 1.0:
        raise ValueError(f"baseline.bendikas.min_success must be in (0, 1], got {cfg.min_success}")
    if int(cfg.window) < 1 or int(cfg.max_frames) < 1:
        raise ValueError(f"baseline.bendikas.window and max_frames must be >= 1, got {cfg.window} and {cfg.max_frames}")


def _copy_adam(optim: torch.optim.Optimizer, src: torch.nn.Module, dst: torch.nn.Module) -> None:
    for a, b in zip(src.parameters(), dst.parameters()):
        state = optim.state.get(a)
        if state:
            optim.state[b] = {k: v.clone() if torch.is_tensor(v) else v for k, v in state.items()}
        else:
            optim.state.pop(b, None)


class SequentialSchedule(RunHook):
    """Moves Bendikas' sub-task on after each iteration (:meth:`update`); state in
    :meth:`state_dict` (the trainer checkpoints it and carries it over a warm start, so a
    pipeline's next phase goes on with the same sub-task and its frame count). A hook on the
    runner (``pnp.training.hooks``)."""

    key = "subtasks"

    def __init__(self, cfg: DictConfig, subtask: SequentialSubtask, actor: StageEnsemble, critic: StageEnsemble,
                 optim: torch.optim.Optimizer):
        check_sequential(cfg)
        if not isinstance(subtask, SequentialSubtask):
            raise TypeError(f"Bendikas' schedule needs the env's SequentialSubtask, got {type(subtask).__name__}")
        if not (isinstance(actor, StageEnsemble) and isinstance(critic, StageEnsemble)):
            raise TypeError("Bendikas' schedule needs per-stage actor and critic ensembles (model.per_stage=bendikas)")
        self.min_success, self.window, self.max_frames = float(cfg.min_success), int(cfg.window), int(cfg.max_frames)
        self.env_subtask, self.actor, self.critic, self.optim = subtask, actor, critic, optim
        self.last = len(actor.members) - 1
        self.rows: list[dict] = []  # this sub-task's recent iterations (success rate, episodes)
        self.frames = 0  # used by this sub-task
        self.frames_total = 0  # over all sub-tasks, across warm starts
        self.history: list[dict] = []  # one record per finished sub-task

    @property
    def subtask(self) -> int:
        return int(self.actor.route[0])

    def sync(self) -> None:
        """The env and the critic to the actor's sub-task (after a restore or warm start)."""
        k = self.subtask
        self.critic.route_all_to(k)
        self.env_subtask.set_subtask(k)

    def on_warm_start(self, runner, init: dict) -> None:
        if self.key in init:  # a pipeline's next phase: the same sub-task
            self.load_state_dict(init[self.key])

    def on_ready(self, runner) -> None:
        self.sync()

    def on_row(self, runner, batch, row: dict) -> dict:
        return self.update(row, batch.numel())  # the sub-task that trained, and whether it ended here

    def update(self, row: dict, frames: int) -> dict:
        """After an iteration of ``frames`` frames with metrics ``row``: move on if the
        sub-task is done. Returns the logged ``subtask`` (the one that trained) and
        ``subtask_exit`` (0 going on, 1 success threshold, 2 frame cap)."""
        k = self.subtask
        self.frames += int(frames)
        self.frames_total += int(frames)
        out = {"subtask": float(k), "subtask_exit": 0.0}
        if k == self.last:
            return out
        self.rows = [*self.rows, {"success_rate": row["success_rate"], "episodes": row["episodes"]}][-self.window:]
        success = windowed_mean(self.rows, "success_rate", self.window)
        why = "success" if success is not None and success >= self.min_success else None
        if why is None and self.frames >= self.max_frames:
            why = "frames"
        if why is not None:
            self.advance(why, success)
            out["subtask_exit"] = float(EXITS[why])
        return out

    def advance(self, why: str, success: float | None = None) -> None:
        """Policy k+1 starts as policy k; the env moves to sub-task k+1."""
        k = self.subtask
        if k == self.last:
            raise ValueError(f"sub-task {k} is the last; there is no next one")
        for net in (self.actor, self.critic):
            net.copy_member(k, k + 1)
            _copy_adam(self.optim, net.members[k], net.members[k + 1])
        self.actor.route_all_to(k + 1)
        self.sync()
        self.history.append({"subtask": k, "exit": why, "frames": self.frames, "frames_total": self.frames_total,
                             "success_rate": success})
        print(f"Bendikas: sub-task {k} ended by {why} after {self.frames} frames "
              f"(success {success if success is None else round(success, 3)}); sub-task {k + 1} starts")
        self.rows, self.frames = [], 0

    def state_dict(self) -> dict:
        return {"rows": list(self.rows), "frames": self.frames, "frames_total": self.frames_total,
                "history": list(self.history)}

    def load_state_dict(self, state: dict) -> None:
        self.rows, self.history = list(state["rows"]), list(state["history"])
        self.frames, self.frames_total = int(state["frames"]), int(state["frames_total"])
