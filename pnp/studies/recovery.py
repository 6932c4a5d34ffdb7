"""The paper's recovery claim, measured (Sec. III-C): the box moved away after it was
lifted, and mocap dropouts, for a student and its teacher on the same trials.

:class:`BoxDisplacement` is a :class:`~pnp.training.rollout.TrialHook`: ``delay_s`` (1 s)
after the box is first lifted in an episode (``object_lifted`` of any robot), it moves the
box ``distance`` (0.5-1 m) in a random direction and sets it down at rest, released
(``PnPEnv.displace_box``); once per episode. Episode k of world w draws its candidate
offsets from a generator seeded by (seed, w, k), so every policy gets the same draws for
the same trial; the first candidate whose box footprint keeps ``clearance`` from every
robot base is taken (a box set down on a robot's legs would measure the physics, not the
policy).

:func:`evaluate_recovery` runs both comparisons: the displacement for the student (its
noisy view), the teacher with the same noise and the teacher on clean observations; the
dropouts (the student's noise with its mocap dropouts made frequent and long) for the
student and the noisy teacher.
"""
from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from torchrl.envs import TransformedEnv

from pnp.task import HL_DT
from pnp.task.geometry import FOOTPRINT_HALF
from pnp.training.checkpoint import load_checkpoint, seed_everything
from pnp.training.collect import seconds
from pnp.distill.config import distill_config
from pnp.training.keys import STAGE
from pnp.training.rollout import GRABBED, LIFTED, evaluation_env_config, run_trials, summarise
from pnp.distill.student import EVALUATIONS, Teacher, load_student_actor, make_student_env

DELAY_S = 1.0  # after the first lift (the "1 s after the box is first lifted")
DISTANCE_M = (0.5, 1.0)
# Box footprint to base centre: the base footprint's half diagonal and 10 cm to spare.
CLEARANCE_M = math.hypot(*FOOTPRINT_HALF) + 0.1
TRIES = 32  # candidate offsets per displacement
PAIRED_TAG = 1 << 40  # keeps the (seed, trial) streams apart from the (seed, world, episode) ones
# The dropout comparison: teacher against student, both on noisy observations.
DROPOUT_RUNS = {"student": "student", "teacher_noisy": "noisy"}


def choose_offsets(u: torch.Tensor, box_xy: torch.Tensor, box_yaw: torch.Tensor, box_half: torch.Tensor,
                   bases: torch.Tensor, distance: tuple[float, float], clearance: float):
    """Per row, the first of the candidate offsets given by uniform draws ``u`` [M, T, 2]
    (direction, distance in ``distance``) that keeps the moved box's footprint (centre
    ``box_xy`` [M, 2], yaw [M], half edges ``box_half`` [M, 2]) at least ``clearance`` from
    every base centre ``bases`` [M, R, 2]; the clearest candidate where none does.
    Returns the offsets [M, 2] and whether each kept the clearance [M]."""
    angle, radius = 2 * math.pi * u[..., 0], distance[0] + (distance[1] - distance[0]) * u[..., 1]
    offsets = radius.unsqueeze(-1) * torch.stack([torch.cos(angle), torch.sin(angle)], -1)  # [M, T, 2]
    rel = bases.unsqueeze(1) - (box_xy.unsqueeze(1) + offsets).unsqueeze(2)  # base from new centre [M, T, R, 2]
    c, s = torch.cos(box_yaw)[:, None, None], torch.sin(box_yaw)[:, None, None]
    lx, ly = c * rel[..., 0] + s * rel[..., 1], c * rel[..., 1] - s * rel[..., 0]  # in the box frame
    ex = (lx.abs() - box_half[:, None, None, 0]).clamp(min=0)
    ey = (ly.abs() - box_half[:, None, None, 1]).clamp(min=0)
    gap = torch.hypot(ex, ey).amin(-1)  # [M, T]
    ok = gap >= clearance
    pick = torch.where(ok.any(-1), ok.float().argmax(-1), gap.argmax(-1))
    rows = torch.arange(len(u))
    return offsets[rows, pick], ok[rows, pick]


class BoxDisplacement:
    """Moves the box once per episode, ``delay_s`` after its first lift (module docstring).

    Adds to each trial record: ``episode`` (of its world), ``lift_step`` and
    ``displaced_step`` (episode steps, ``None`` if it never came), ``displacement_m``,
    ``clear`` (the clearance was kept), ``stage_at_displacement``, ``regrasped`` and
    ``relifted`` (``object_grabbed`` / ``object_lifted`` of any robot at a step after the
    displacement) and ``stage_history``: ``[steps after the displacement, stage]`` at the
    displacement and at every change of the highest robot stage after it. ``events`` lists
    every displacement as ``(world, episode, step)``."""

    def __init__(self, num_worlds: int, seed: int, delay_s: float = DELAY_S,
                 distance: tuple[float, float] = DISTANCE_M, clearance: float = CLEARANCE_M):
        if not delay_s >= 0:
            raise ValueError(f"displacement delay_s must be >= 0, got {delay_s}")
        lo, hi = (float(d) for d in distance)
        if not 0 <= lo <= hi:
            raise ValueError(f"displacement distance must be [lo, hi] with 0 <= lo <= hi (m), got {list(distance)}")
        if not clearance >= 0:
            raise ValueError(f"displacement clearance must be >= 0, got {clearance}")
        self.num_worlds, self.seed, self.delay = num_worlds, int(seed), round(delay_s / HL_DT)
        self.distance, self.clearance = (lo, hi), float(clearance)
        n = num_worlds
        self.episode = torch.zeros(n, dtype=torch.long)
        self.lift_step, self.displaced_step = torch.full((n,), -1), torch.full((n,), -1)  # -1: not yet
        self.stage = torch.full((n,), -1)  # the highest robot stage last seen after the displacement
        self.regrasped, self.relifted = torch.zeros(n, dtype=torch.bool), torch.zeros(n, dtype=torch.bool)
        self.history: list[list[list[int]]] = [[] for _ in range(n)]
        self.info: list[dict] = [{} for _ in range(n)]
        self.events: list[tuple[int, int, int]] = []

    def _draws(self, env, world: int) -> torch.Tensor:
        # Paired trials: the direction depends on (seed, trial) alone, as the layout does.
        if getattr(env, "paired_trials", False):
            entropy = [self.seed, PAIRED_TAG, int(env.trial[world])]
        else:
            entropy = [self.seed, world, int(self.episode[world])]
        key = np.random.SeedSequence(entropy).generate_state(1)[0]
        return torch.rand(TRIES, 2, generator=torch.Generator().manual_seed(int(key)))

    def after_step(self, env: TransformedEnv, nxt: TensorDictBase) -> None:
        n = self.num_worlds
        step = nxt["step_count"].view(n)
        cond = nxt["agents", "stage_conditions"]
        stage = nxt[STAGE].reshape(n, -1).max(-1).values
        after = self.displaced_step >= 0  # this step's state came after the displacement
        self.regrasped |= after & cond[..., GRABBED].any(-1)
        self.relifted |= after & cond[..., LIFTED].any(-1)
        for w in (after & (stage != self.stage)).nonzero().view(-1).tolist():
            self.history[w].append([int(step[w] - self.displaced_step[w]), int(stage[w])])
        self.stage = torch.where(after, stage, self.stage)
        first = cond[..., LIFTED].any(-1) & (self.lift_step < 0)
        self.lift_step = torch.where(first, step, self.lift_step)
        due = (self.lift_step >= 0) & (self.displaced_step < 0) & (step >= self.lift_step + self.delay)
        due &= ~nxt["done"].view(n)  # an ended episode's world is already reset
        if due.any():
            self._displace(env.base_env, due.nonzero().view(-1), step, stage)

    def _displace(self, env, worlds: torch.Tensor, step: torch.Tensor, stage: torch.Tensor) -> None:
        s = env.physical_state()
        rot = s.box_rot[worlds]
        offsets, clear = choose_offsets(
            torch.stack([self._draws(env, w) for w in worlds.tolist()]), s.box_pos[worlds, :2],
            torch.atan2(rot[:, 1, 0], rot[:, 0, 0]), s.box_size[worlds, :2] * 0.5, s.base[worlds, :, :2],
            self.distance, self.clearance)
        env.displace_box(worlds, offsets)
        for i, w in enumerate(worlds.tolist()):
            self.displaced_step[w], self.stage[w] = step[w], stage[w]
            self.history[w] = [[0, int(stage[w])]]
            self.info[w] = {"displacement_m": float(offsets[i].norm()), "clear": bool(clear[i]),
                            "stage_at_displacement": int(stage[w])}
            self.events.append((w, int(self.episode[w]), int(step[w])))

    def record(self, world: int) -> dict:
        step = lambda t: int(t) if t >= 0 else None  # noqa: E731
        info = self.info[world] or {"displacement_m": None, "clear": None, "stage_at_displacement": None}
        return {"episode": int(self.episode[world]), "lift_step": step(self.lift_step[world]),
                "displaced_step": step(self.displaced_step[world]), **info,
                "regrasped": bool(self.regrasped[world]), "relifted": bool(self.relifted[world]),
                "stage_history": list(self.history[world])}

    def reset(self, done: torch.Tensor) -> None:
        self.episode += done.long()
        for t in (self.lift_step, self.displaced_step, self.stage):
            t[done] = -1
        self.regrasped[done], self.relifted[done] = False, False
        for w in done.nonzero().view(-1).tolist():
            self.history[w], self.info[w] = [], {}


def _mean_std(values: list[float]) -> tuple[float | None, float | None]:
    return (float(np.mean(values)), float(np.std(values))) if values else (None, None)


def recovery_summary(records: list[dict]) -> dict:
    """``summarise``'s figures, then those of the displaced trials: ``recovery_rate`` (their
    success rate), ``regrasp_rate``, ``relift_rate``, and the time from displacement to
    success; and the per-trial records."""
    moved = [r for r in records if r["displaced_step"] is not None]
    rate = lambda key: float(np.mean([r[key] for r in moved])) if moved else None  # noqa: E731
    mean, std = _mean_std([seconds(r["steps"] - r["displaced_step"]) for r in moved if r["success"]])
    return {**summarise(records), "displaced": len(moved),
            "never_lifted": sum(r["lift_step"] is None for r in records),
            "displaced_without_clearance": sum(not r["clear"] for r in moved), "recovery_rate": rate("success"),
            "regrasp_rate": rate("regrasped"), "relift_rate": rate("relifted"),
            "recovery_time_mean_s": mean, "recovery_time_std_s": std, "records": records}


def dropout_config(cfg: DictConfig, p: float, min_s: float, max_s: float, fields) -> DictConfig:
    """A copy of the student configuration ``cfg`` with its mocap dropouts replaced."""
    if not 0 < float(p) <= 1:
        raise ValueError(f"dropout.p must be in (0, 1] (the dropout comparison needs dropouts), got {p}")
    if not 0 <= float(min_s) <= float(max_s):
        raise ValueError(f"dropout needs 0 <= min_s <= max_s, got min_s={min_s}, max_s={max_s}")
    out = copy.deepcopy(cfg)
    out.noise.dropout.p, out.noise.dropout.min_s, out.noise.dropout.max_s = float(p), float(min_s), float(max_s)
    out.noise.dropout.fields = list(fields)
    return out


def _trials(cfg: DictConfig, ckpt: dict, name: str, view: str, trials: int, seed: int, progress: bool,
            hook: BoxDisplacement | None = None) -> list[dict]:
    seed_everything(seed)
    env = make_student_env(cfg, seed, view)
    actor = load_student_actor(cfg, env, ckpt) if name == "student" else Teacher(cfg, env).actor
    try:
        return run_trials(env, actor, trials, progress, hook=hook)
    finally:
        env.close()


def evaluate_recovery(path: str | Path, trials: int, num_worlds: int, seed: int, displacement: dict,
                      dropout: dict, progress: bool = False, **env_overrides) -> tuple[DictConfig, dict, dict]:
    """Both comparisons over ``trials`` deterministic episodes per policy, in evaluation envs
    (``rollout.evaluation_env_config``) built alike from ``seed``. ``displacement``:
    :class:`BoxDisplacement`'s ``delay_s``, ``distance``, ``clearance``; ``dropout``:
    :func:`dropout_config`'s ``p``, ``min_s``, ``max_s``, ``fields``. Returns the evaluation
    configuration (the displacement runs'; the dropout runs change only ``noise.dropout``),
    the student checkpoint and ``{"displacement": {policy: figures}, "dropout": {policy:
    figures}}``."""
    ckpt = load_checkpoint(Path(path))
    cfg = distill_config(ckpt["cfg"])
    evaluation_env_config(cfg.env, num_worlds, **env_overrides)
    out = {"displacement": {}, "dropout": {}}
    for name, view in EVALUATIONS.items():
        hook = BoxDisplacement(int(cfg.env.num_worlds), seed, **displacement)
        out["displacement"][name] = recovery_summary(_trials(cfg, ckpt, name, view, trials, seed, progress, hook))
    dcfg = dropout_config(cfg, **dropout)
    for name, view in DROPOUT_RUNS.items():
        out["dropout"][name] = summarise(_trials(dcfg, ckpt, name, view, trials, seed, progress))
    return cfg, ckpt, out
