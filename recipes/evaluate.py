"""Evaluate a trained teacher over N trials with the deterministic policy (paper Table I).

    python recipes/evaluate.py                                   # newest runs/**/checkpoint.pt, 500 trials
    python recipes/evaluate.py checkpoint=runs/<run> trials=100 env.backend=kinematic out=results/eval.json

Episodes start from the env's randomised layouts (seeded by ``seed``) and end on success,
a fall or the 45 s limit. With W worlds each world runs ceil(N / W) episodes; the first N
to finish (by step, then world index) are the trials. Writes a JSON file and a markdown
table in the format of Table I (default: beside the checkpoint, ``eval_<backend>.json|md``).

Failure causes: every failed trial gets exactly one, the first that applies of

* ``fall``: the episode terminated without success because a robot fell (the env's fall
  term, base below ``pnp.task.FALL_HEIGHT``, is set at the last step);
* ``diverged``: the physics diverged and the env restarted the world (MuJoCo only);
* ``dropped_box``: the box was lifted at some step of the episode (stage condition
  ``object_lifted`` held for some robot), success was never reached, and at the last step
  no robot holds it (``object_grabbed`` false for all) and its centre is at least
  ``GOAL_RADIUS`` from the goal: a box nobody holds lies on the floor, outside the goal;
* ``timeout``: every other failure; the time limit passed (box never lifted, still held,
  or set down inside the goal but not released).

Completion time is steps x 0.1 s over successful trials (mean and population std).

``sample=[ee]`` (or ``base``, ``grip``, ``all``) is a diagnostic, not the paper's metric:
those action groups are drawn from the policy's distribution, the rest stay at the mean.
It measures what the deterministic policy loses to the noise it was trained with.
"""
from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import hydra
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tensordict.nn import InteractionType, set_interaction_type
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import (  # noqa: E402
    ACTION, N_STAGES, ObsNorm, fold_constant_inputs, load_checkpoint, make_env, make_models, resolve_checkpoint, seconds, seed_everything,
)
from _provenance import provenance  # noqa: E402

from pnp.layout import START_RANGE  # noqa: E402
from pnp.scene import GOAL_RADIUS  # noqa: E402
from pnp.task import ACTION_NAMES, EPISODE_S, HL_DT  # noqa: E402
from pnp.terms import CONDITIONS, REWARD_TERMS  # noqa: E402

LIFTED, GRABBED = CONDITIONS.index("object_lifted"), CONDITIONS.index("object_grabbed")
FALL = REWARD_TERMS.index("fall")
CAUSES = ("fall", "diverged", "dropped_box", "timeout")
_AI = ACTION_NAMES.index
ACTION_GROUPS = {"base": slice(_AI("base_vx"), _AI("base_wz") + 1), "ee": slice(_AI("ee_x"), _AI("ee_yaw") + 1),
                 "grip": slice(_AI("grasp"), _AI("grasp") + 1), "all": slice(0, len(ACTION_NAMES))}


def _end_records(nxt, worlds: torch.Tensor, lifted: torch.Tensor, peak: torch.Tensor, step: int) -> list[dict]:
    """One record per world in ``worlds`` whose episode ended at this step."""
    cond = nxt["agents", "stage_conditions"][worlds]
    box_goal = (nxt["agents", "object"][worlds, 0, :2] - nxt["agents", "goal"][worlds, 0, :2]).norm(dim=-1)
    fell = nxt["agents", "reward_terms"][worlds][..., FALL].bool().any(-1)
    success = nxt["success"][worlds, 0]
    held = cond[..., GRABBED].any(-1)
    dropped = lifted[worlds] & ~held & (box_goal >= GOAL_RADIUS)
    rows = []
    for i, w in enumerate(worlds.tolist()):
        cause = None
        if not success[i]:
            flags = {"fall": bool(fell[i]) and bool(nxt["terminated"][w, 0]), "diverged": bool(nxt["diverged"][w, 0]),
                     "dropped_box": bool(dropped[i])}
            cause = next((c for c in CAUSES[:-1] if flags[c]), "timeout")
        rows.append({"world": w, "end_step": step, "success": bool(success[i]), "cause": cause,
                     "steps": int(nxt["step_count"][w, 0]), "end_stage": int(nxt["agents", "stage"][w].max()),
                     "peak_stage": int(peak[w])})
    return rows


def _check_groups(sample) -> tuple[str, ...]:
    groups = tuple(sample or ())
    bad = [g for g in groups if g not in ACTION_GROUPS]
    if bad:
        raise ValueError(f"sample: unknown action group(s) {bad}; choose from {sorted(ACTION_GROUPS)}")
    return groups


def _act(actor, td, groups: tuple[str, ...]):
    """The mean action, with the entries of ``groups`` replaced by a draw from the policy."""
    td = actor(td)
    if not groups:
        return td
    drawn = actor[-1].get_dist(td).sample()  # from the loc/scale just written: no second forward
    action = td[ACTION].clone()
    for g in groups:
        action[..., ACTION_GROUPS[g]] = drawn[..., ACTION_GROUPS[g]]
    return td.set(ACTION, action)


def run_trials(env, actor, trials: int, progress: bool = False, sample=None) -> list[dict]:
    """Exactly ``trials`` episodes with the deterministic (mean) action, in finishing order
    (``sample``: action groups drawn from the policy instead, a diagnostic)."""
    groups = _check_groups(sample)
    n_worlds = env.base_env.num_worlds
    per_world = math.ceil(trials / n_worlds)
    count = torch.zeros(n_worlds, dtype=torch.long)
    lifted = torch.zeros(n_worlds, dtype=torch.bool)
    peak = torch.zeros(n_worlds, dtype=torch.long)  # highest stage of any robot in the episode
    records, step = [], 0
    bar = tqdm(total=trials, disable=not progress, desc="trials")
    td = env.reset()
    with torch.no_grad(), set_interaction_type(InteractionType.DETERMINISTIC):
        while bool((count < per_world).any()):
            td = _act(actor, td, groups)
            out, td = env.step_and_maybe_reset(td)
            nxt, step = out["next"], step + 1
            lifted |= nxt["agents", "stage_conditions"][..., LIFTED].any(-1)
            peak = torch.maximum(peak, nxt["agents", "stage"].reshape(n_worlds, -1).max(-1).values)
            done = nxt["done"].view(n_worlds)
            worlds = (done & (count < per_world)).nonzero().view(-1)
            if len(worlds):
                records += _end_records(nxt, worlds, lifted, peak, step)
                count[worlds] += 1
                bar.update(min(len(worlds), max(0, trials - bar.n)))
            lifted &= ~done
            peak[done] = 0
    bar.close()
    records.sort(key=lambda r: (r["end_step"], r["world"]))
    return records[:trials]


def summarise(records: list[dict]) -> dict:
    times = np.array([seconds(r["steps"]) for r in records if r["success"]])
    stages = np.bincount([r["end_stage"] for r in records], minlength=N_STAGES)
    peaks = np.bincount([r["peak_stage"] for r in records], minlength=N_STAGES)
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


def table_md(result: dict, method: str) -> str:
    """A Table I row: Method | Success rate (%) | Completion time (s)."""
    t = result["completion_time_mean_s"]
    time_s = "-" if t is None else f"{t:.2f} ± {result['completion_time_std_s']:.2f}"
    group = "Single-robot PnP" if result["num_robots"] == 1 else "Dual-robot PnP"
    causes = ", ".join(f"{k} {v}" for k, v in result["failure_causes"].items())
    return (
        "| Method | Success rate (%) | Completion time (s) |\n| --- | --- | --- |\n"
        f"| *{group}* | | |\n| {method} | {100 * result['success_rate']:.1f} | {time_s} |\n\n"
        f"{result['trials']} trials on the {result['backend']} backend, seed {result['seed']}, starts "
        f"{result['start_range_m'][0]}-{result['start_range_m'][1]} m from the goal; failures: {causes}.\n"
        f"Checkpoint `{result['checkpoint']}` (iteration {result['checkpoint_iteration']}).\n"
    )


def load_policy(ckpt_path: Path, eval_env: DictConfig, num_worlds: int, seed: int):
    """The checkpoint's actor in an evaluation env (terminates at success, gripper by
    threshold, the paper's layouts unless ``eval_env.start_range``):
    ``(env, actor, ckpt, env_cfg, folded)``."""
    ckpt = load_checkpoint(ckpt_path)
    tcfg = OmegaConf.create(ckpt["cfg"])
    if tcfg.env.get("task", "pnp") != "pnp":
        raise ValueError(f"{ckpt_path} was trained on env.task={tcfg.env.task!r}; this recipe evaluates pnp "
                         "(the EE-tracking ablation evaluates in recipes/ablation_ee.py)")
    env_cfg = tcfg.env.copy()
    env_cfg.backend = eval_env.backend or tcfg.env.backend
    env_cfg.num_worlds = num_worlds
    env_cfg.nthread, env_cfg.max_episode_steps = eval_env.nthread, eval_env.max_episode_steps
    # The paper's layouts unless asked otherwise: a policy trained on near starts is judged on all.
    env_cfg.start_range = list(eval_env.get("start_range") or START_RANGE)
    env_cfg.grasp_sampling = "threshold"  # the deterministic policy's gripper command
    env_cfg.terminate_on_success = True  # a trial ends at its success (completion time)
    seed_everything(seed)
    env = make_env(env_cfg, tcfg.curriculum, seed)
    actor, *_ = make_models(tcfg.model, env, tcfg.loss.value_norm, float(tcfg.loss.popart_beta))
    actor.load_state_dict(ckpt["actor"])
    folded = []
    net = actor.module[0].module
    if env_cfg.backend != tcfg.env.backend and isinstance(net.obs_norm, ObsNorm):
        # Inputs constant on the training backend (the kinematic one has no wrist roll, box
        # tilt or tilt rates) move here; their untrained first-layer weights would scramble
        # the policy. Folding keeps its function on the training data and blinds it to them.
        folded = fold_constant_inputs(net.obs_norm, [net])
    return env, actor, ckpt, env_cfg, folded


def evaluate(cfg: DictConfig) -> dict:
    ckpt_path = resolve_checkpoint(cfg.checkpoint, cfg.runs_root)
    t0 = time.monotonic()
    env, actor, ckpt, env_cfg, folded = load_policy(ckpt_path, cfg.env, min(int(cfg.env.num_worlds), int(cfg.trials)),
                                                    int(cfg.seed))
    tcfg = OmegaConf.create(ckpt["cfg"])
    sample = _check_groups(cfg.get("sample"))
    records = run_trials(env, actor, int(cfg.trials), bool(cfg.progress), sample)
    env.close()
    result = {
        "backend": env_cfg.backend, "num_robots": int(env_cfg.num_robots), "num_worlds": int(env_cfg.num_worlds),
        "start_range_m": [float(x) for x in env_cfg.start_range],
        "max_episode_s": seconds(env_cfg.max_episode_steps or round(EPISODE_S / HL_DT)),
        **summarise(records), "seed": int(cfg.seed), "checkpoint": str(ckpt_path),
        "checkpoint_iteration": int(ckpt["counters"]["iteration"]), "checkpoint_frames": int(ckpt["counters"]["frames"]),
        # This run's training (a warm-started run's source trained before: see warm_started_from).
        "env_steps": int(ckpt["counters"]["frames"]), "train_wall_s": float(ckpt["counters"]["wall_s"]),
        "warm_started_from": tcfg.get("warm_start"), "trained_backend": tcfg.env.backend,
        "folded_inputs": folded, "sampled_actions": list(sample),
        "schedule": tcfg.curriculum.schedule if tcfg.curriculum.stage_rewards else "none",
        "wall_s": time.monotonic() - t0, **provenance(),
    }
    out = Path(cfg.out) if cfg.out else ckpt_path.parent / f"eval_{env_cfg.backend}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    method = cfg.method or f"Ours ({result['schedule']} curriculum, {result['backend']})" + (
        f", sampled {'+'.join(sample)}" if sample else "")
    out.with_suffix(".md").write_text(table_md(result, method))
    result["json"], result["markdown"] = str(out), str(out.with_suffix(".md"))
    return result


@hydra.main(config_path="config", config_name="evaluate", version_base="1.3")
def main(cfg: DictConfig) -> None:
    result = evaluate(cfg)
    print(Path(result["markdown"]).read_text())
    print(f"wrote {result['json']}")


if __name__ == "__main__":
    main()
