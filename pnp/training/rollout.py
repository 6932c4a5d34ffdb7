"""One rollout API for everything that runs a trained policy: evaluation, the ablation,
rendering and the analysis scripts.

:func:`load_policy` puts a checkpoint's actor in an evaluation env (with env overrides);
:func:`run_trials` runs exactly N deterministic episodes and classifies each failure;
:func:`summarise` turns the trial records into the Table I figures.

Failure causes: every failed trial gets exactly one, the first that applies of

* ``fall``: the episode terminated without success because a robot fell;
* ``diverged``: the physics diverged and the env restarted the world (MuJoCo only);
* ``dropped_box``: the box was lifted at some step (``object_lifted`` held for some
  robot), success never came, and at the last step no robot holds it and its centre is
  at least ``GOAL_RADIUS`` from the goal;
* ``timeout``: every other failure (box never lifted, still held, or set down inside the
  goal but not released).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from tensordict.nn import InteractionType, ProbabilisticTensorDictSequential, set_interaction_type
from torchrl.envs import TransformedEnv
from tqdm import tqdm

from pnp.sim.layout import START_RANGE, trial_generator
from pnp.sim.scene import GOAL_RADIUS
from pnp.task import ACTION_NAMES, OBS_FIELDS
from pnp.task.terms import CONDITIONS, REWARD_TERMS, STAGES
from pnp.training.checkpoint import load_checkpoint, seed_everything
from pnp.training.collect import seconds
from pnp.training.config import KinematicOptions
from pnp.training.migration import migrate
from pnp.training.keys import ACTION, STAGE
from pnp.training.models import Models, ObsNorm, dist_from_params, fold_constant_inputs, make_models
from pnp.training.recurrent import carry_state, init_state, recurrent_net
from pnp.training.tasks import make_env

LIFTED, GRABBED = CONDITIONS.index("object_lifted"), CONDITIONS.index("object_grabbed")
FALL = REWARD_TERMS.index("fall")
# tipped_box: the box lies unheld on its side (up axis beyond 60 deg) without having been
# lifted and dropped; most MuJoCo timeouts of run 6 ended so (docs/history/pipeline_single/failures.md).
CAUSES = ("fall", "diverged", "dropped_box", "tipped_box", "timeout")
TIPPED_TILT = math.pi / 3  # rad
_BOX_X, _BOX_Y = OBS_FIELDS["object"]["box_x_axis"], OBS_FIELDS["object"]["box_y_axis"]
_AI = ACTION_NAMES.index
ACTION_GROUPS = {"base": slice(_AI("base_vx"), _AI("base_wz") + 1), "ee": slice(_AI("ee_x"), _AI("ee_yaw") + 1),
                 "grip": slice(_AI("grasp"), _AI("grasp") + 1), "all": slice(0, len(ACTION_NAMES))}


@dataclass
class LoadedPolicy:
    """A checkpoint's actor in the env it is evaluated in."""

    env: TransformedEnv
    actor: ProbabilisticTensorDictSequential
    ckpt: dict
    cfg: DictConfig  # the training configuration (migrated), with ``cfg.env`` the evaluation env's
    folded: list[int] = field(default_factory=list)  # observation entries blinded by the backend change


def evaluation_env_config(env: DictConfig, num_worlds: int, **env_overrides) -> DictConfig:
    """A training ``env`` config changed, in place, into the evaluation env's: terminate at
    success, start from the paper's layouts, then
    ``env_overrides`` (``None`` values keep the default); returns it."""
    env.num_worlds, env.max_episode_steps = int(num_worlds), None
    env.start_range = list(START_RANGE)  # a policy trained on near starts is judged on all
    env.terminate_on_success = True  # a trial ends at its success (completion time)
    env.paired_trials = True  # trial i's layout from (seed, i) alone (docs/guide/evaluation.md)
    for key, value in env_overrides.items():
        if key not in env:
            raise ValueError(f"evaluation: unknown env override {key!r}; env keys are {sorted(env)}")
        if value is not None:  # a mapping (kinematic options) changes only the keys it names
            OmegaConf.update(env, key, value, merge=isinstance(value, (dict, DictConfig)))
    if env.backend != "kinematic":
        # Stand-ins for MuJoCo's contacts: a MuJoCo evaluation has the real ones.
        env.kinematic = OmegaConf.structured(KinematicOptions)
    else:
        env.finger_speed = None  # MuJoCo's fingers only
    return env


def load_policy(checkpoint: str | Path, num_worlds: int, seed: int, **env_overrides) -> LoadedPolicy:
    """The checkpoint's actor in an evaluation env: the training env, changed to terminate
    at success, close the gripper by threshold and start from the paper's layouts, then by
    ``env_overrides`` (``backend``, ``start_range``, ``max_episode_steps``, ``nthread``, ...;
    ``None`` values keep the default)."""
    ckpt = load_checkpoint(Path(checkpoint))
    cfg = migrate(ckpt["cfg"])
    env = evaluation_env_config(cfg.env, num_worlds, **env_overrides)
    seed_everything(seed)
    tenv = make_env(env, cfg.curriculum, seed)
    models, folded = trained_models(ckpt, cfg, tenv, env.backend)
    return LoadedPolicy(tenv, models.actor, ckpt, cfg, folded)


def trained_models(ckpt: dict, cfg: DictConfig, env: TransformedEnv, backend: str) -> tuple[Models, list[int]]:
    """A teacher checkpoint's models in ``env`` (built from ``cfg``, its actor's weights loaded)
    and the observation entries folded because ``env`` runs on ``backend``, not the one the
    checkpoint trained on:
    inputs constant on the training backend (the kinematic one has no wrist roll, box tilt or
    tilt rates) move here, and their untrained first-layer weights would scramble the policy.
    Folding keeps its function on the training data and blinds it to them."""
    models = make_models(cfg.model, cfg.loss, env)
    models.actor.load_state_dict(ckpt["actor"])
    folded = []
    if backend != ckpt["cfg"]["env"]["backend"] and isinstance(models.obs_norm, ObsNorm):
        folded = fold_constant_inputs(models.obs_norm, [models.actor_net])
    return models, folded


class TrialNoise:
    """Draws from the policy that depend on (evaluation seed, trial, step in the trial) alone, so
    a sampled evaluation stays paired: trial i meets the same noise whatever the world count or
    the order in which episodes end (the global stream would hand it to whichever world is next)."""

    STREAM = 1  # keeps these draws apart from the layouts' stream of the same (seed, trial)

    def __init__(self, base_env):
        self.base = base_env

    def seeds(self, steps: torch.Tensor) -> list[int]:
        """One seed per world from its trial and ``steps`` [W] (steps taken in the trial)."""
        return [trial_generator(self.base._trial_seed, t, k, self.STREAM).initial_seed()
                for t, k in zip(self.base.trial.tolist(), steps.tolist())]

    def draw(self, actor, td: TensorDictBase) -> torch.Tensor:
        rows = []
        for w, seed in enumerate(self.seeds(td["step_count"].reshape(len(td), -1)[:, 0])):
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(seed)
                rows.append(dist_from_params(actor, td[w:w + 1]).sample())
        return torch.cat(rows)


def _act(actor, td: TensorDictBase, groups: tuple[str, ...], noise: TrialNoise | None = None) -> TensorDictBase:
    """The mean action, with the entries of ``groups`` replaced by a draw from the policy
    (``noise``: per-trial draws; else the global stream)."""
    td = actor(td)
    if not groups:
        return td
    # From the loc/scale just written: no second forward.
    drawn = noise.draw(actor, td) if noise is not None else dist_from_params(actor, td).sample()
    action = td[ACTION].clone()
    for g in groups:
        action[..., ACTION_GROUPS[g]] = drawn[..., ACTION_GROUPS[g]]
    return td.set(ACTION, action)


def check_groups(sample) -> tuple[str, ...]:
    groups = tuple(sample or ())
    bad = [g for g in groups if g not in ACTION_GROUPS]
    if bad:
        raise ValueError(f"sample: unknown action group(s) {bad}; choose from {sorted(ACTION_GROUPS)}")
    return groups


def box_up_z(obj: torch.Tensor) -> torch.Tensor:
    """cos of the box's tilt from object blocks ``[..., 30]``: (x axis cross y axis)_z, which a
    base frame (yawed only) keeps as the world's."""
    x, y = obj[..., _BOX_X], obj[..., _BOX_Y]
    return x[..., 0] * y[..., 1] - x[..., 1] * y[..., 0]


def classify_failures(nxt: TensorDictBase, worlds: torch.Tensor, lifted: torch.Tensor) -> list[str | None]:
    """The failure cause of each world in ``worlds`` whose episode ended at this step
    (``None`` for a success); ``lifted`` [N]: the box was lifted in the episode."""
    agents = nxt["agents"]
    if "object" in agents.keys():  # pick-and-place
        box_goal = (agents["object"][worlds, 0, :2] - agents["goal"][worlds, 0, :2]).norm(dim=-1)
        held = agents["stage_conditions"][worlds][..., GRABBED].any(-1)
        dropped = lifted[worlds] & ~held & (box_goal >= GOAL_RADIUS)
        tipped = ~held & (box_up_z(agents["object"][worlds, 0]) < math.cos(TIPPED_TILT))
        fell = agents["reward_terms"][worlds][..., FALL].bool().any(-1)
    else:  # no box, no fall term (EE tracking)
        dropped = tipped = fell = torch.zeros(len(worlds), dtype=torch.bool)
    causes = []
    for i, w in enumerate(worlds.tolist()):
        if bool(nxt["success"][w, 0]):
            causes.append(None)
            continue
        flags = {"fall": bool(fell[i]) and bool(nxt["terminated"][w, 0]), "diverged": bool(nxt["diverged"][w, 0]),
                 "dropped_box": bool(dropped[i]), "tipped_box": bool(tipped[i])}
        causes.append(next((c for c in CAUSES[:-1] if flags[c]), "timeout"))
    return causes


class TrialHook(Protocol):
    """Something that acts on the env during trials (a disturbance) and adds to their records."""

    def after_step(self, env: TransformedEnv, nxt: TensorDictBase) -> None:
        """After every step, before its finished episodes are recorded (their worlds are
        already reset)."""

    def record(self, world: int) -> dict:
        """Extra entries of the record of ``world``'s episode that just ended."""

    def reset(self, done: torch.Tensor) -> None:
        """The episodes of the worlds in ``done`` (bool [W]) ended."""


def run_trials(env: TransformedEnv, actor, trials: int, progress: bool = False, sample=None,
               hook: TrialHook | None = None) -> list[dict]:
    """Exactly ``trials`` episodes with the deterministic (mean) action (``sample``: action
    groups drawn from the policy instead, a diagnostic, per trial on a paired env (:class:`TrialNoise`);
    ``hook``: see :class:`TrialHook`).

    On an env with ``paired_trials`` (evaluation), the trials are trials 0..N-1 of the env's
    seed, whatever the world count: records come back in trial order, each with its
    ``trial``. Otherwise each of W worlds runs ceil(N / W) episodes and the first N to finish
    (by step, then world index) are the trials. One record per trial: world, end step,
    success, cause, steps, end stage and peak stage (highest of any robot), and the hook's entries."""
    groups = check_groups(sample)
    base = env.base_env
    n_worlds, paired = base.num_worlds, bool(getattr(base, "paired_trials", False))
    per_world = math.ceil(trials / n_worlds)
    count = torch.zeros(n_worlds, dtype=torch.long)
    lifted = torch.zeros(n_worlds, dtype=torch.bool)
    peak = torch.zeros(n_worlds, dtype=torch.long)
    records, step = [], 0
    bar = tqdm(total=trials, disable=not progress, desc="trials")
    td, recurrent = init_state(env.reset(), actor), recurrent_net(actor) is not None
    noise = TrialNoise(base) if groups and paired else None
    with torch.no_grad(), set_interaction_type(InteractionType.DETERMINISTIC):
        while len(records) < trials if paired else bool((count < per_world).any()):
            running = base.trial.clone() if paired else None  # done worlds are reset within the step
            td = _act(actor, td, groups, noise)
            out, td = env.step_and_maybe_reset(td)
            if recurrent:
                carry_state(out, td)
            nxt, step = out["next"], step + 1
            if hook is not None:
                hook.after_step(env, nxt)
            if "object" in nxt["agents"].keys():  # pick-and-place: the box's lift
                lifted |= nxt["agents", "stage_conditions"][..., LIFTED].any(-1)
            stage = nxt[STAGE].reshape(n_worlds, -1).max(-1).values
            peak = torch.maximum(peak, stage)
            done = nxt["done"].view(n_worlds)
            keep = (running < trials) if paired else (count < per_world)
            worlds = (done & keep).nonzero().view(-1)
            if len(worlds):
                for w, cause in zip(worlds.tolist(), classify_failures(nxt, worlds, lifted)):
                    records.append({"world": w, "end_step": step, "success": cause is None, "cause": cause,
                                    "steps": int(nxt["step_count"][w, 0]), "end_stage": int(stage[w]),
                                    "peak_stage": int(peak[w]), **({"trial": int(running[w])} if paired else {}),
                                    **(hook.record(w) if hook is not None else {})})
                count[worlds] += 1
                bar.update(min(len(worlds), max(0, trials - bar.n)))
            lifted &= ~done
            peak[done] = 0
            if hook is not None:
                hook.reset(done)
    bar.close()
    if paired:
        return sorted(records, key=lambda r: r["trial"])
    records.sort(key=lambda r: (r["end_step"], r["world"]))
    return records[:trials]


def summarise(records: list[dict], n_stages: int = len(STAGES)) -> dict:
    """Success rate, completion time (mean and population std over successes), failure
    causes, and end/peak stage counts of the trial records."""
    times = np.array([seconds(r["steps"]) for r in records if r["success"]])
    stages = np.bincount([r["end_stage"] for r in records], minlength=n_stages)
    peaks = np.bincount([r["peak_stage"] for r in records], minlength=n_stages)
    return {
        "trials": len(records),
        "success_rate": float(np.mean([r["success"] for r in records])) if records else math.nan,
        "completion_time_mean_s": float(times.mean()) if len(times) else None,
        "completion_time_std_s": float(times.std()) if len(times) else None,
        "failure_causes": {c: sum(r["cause"] == c for r in records) for c in CAUSES},
        "mean_end_stage": float(np.mean([r["end_stage"] for r in records])) if records else math.nan,
        "end_stage_counts": {f"S{i}": int(c) for i, c in enumerate(stages)},
        "peak_stage_counts": {f"S{i}": int(c) for i, c in enumerate(peaks)},
    }
