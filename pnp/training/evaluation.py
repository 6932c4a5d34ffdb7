"""Evaluate a trained teacher over N trials with the deterministic policy (paper Table I).

    python recipes/evaluate.py                                   # newest runs/**/checkpoint.pt, 500 trials
    python recipes/evaluate.py checkpoint=runs/<run> trials=100 env.backend=kinematic out=runs/eval.json
    python recipes/evaluate.py checkpoint=runs/main selected=true  # the checkpoint recipes/select_checkpoint.py chose

Episodes start from the env's randomised layouts (seeded by ``seed``) and end on success,
a fall or the 45 s limit; failure causes and trial selection are described in
``pnp.training.rollout``. Writes a JSON file and a markdown table in the format of
Table I (default: beside the checkpoint, ``eval_<backend>.json|md``).

``sample=[ee]`` (or ``base``, ``grip``, ``all``) is a diagnostic, not the paper's metric:
those action groups are drawn from the policy's distribution, the rest stay at the mean.
"""
from __future__ import annotations

import time
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from pnp.task import EPISODE_S, HL_DT
from pnp.training.checkpoint import load_checkpoint, resolve_checkpoint
from pnp.training.collect import seconds
from pnp.training.pipeline import load_launches, load_state
from pnp.training.paired import comparison_md, paired_comparison, trial_table
from pnp.training.protocol import resolve_seed
from pnp.studies.recovery import CLEARANCE_M, DELAY_S, DISTANCE_M, BoxDisplacement, recovery_summary
from pnp.training.provenance import check_clean, evaluation_record, write_result
from pnp.training.rollout import check_groups, load_policy, run_trials, summarise
from pnp.training.selection import SELECTION, selected_checkpoint
from pnp.distill.student import add_observation_noise


def table_md(result: dict, method: str) -> str:
    """A Table I row: Method | Success rate (%) | Completion time (s)."""
    t = result["completion_time_mean_s"]
    time_s = "-" if t is None else f"{t:.2f} ± {result['completion_time_std_s']:.2f}"
    group = "Single-robot PnP" if result["num_robots"] == 1 else "Dual-robot PnP"
    causes = ", ".join(f"{k} {v}" for k, v in result["failure_causes"].items())
    return (
        "| Method | Success rate (%) | Completion time (s) |\n| --- | --- | --- |\n"
        f"| *{group}* | | |\n| {method} | {100 * result['success_rate']:.1f} | {time_s} |\n\n"
        f"{result['trials']} paired trials on the {result['backend']} backend, seed {result['seed']} ({result['seed_role']}), starts "
        f"{result['start_range_m'][0]}-{result['start_range_m'][1]} m from the goal; failures: {causes}.\n"
        f"Checkpoint `{result['checkpoint']}` (iteration {result['checkpoint_iteration']})"
        + (f"; legs: `{result['low_level_checkpoint']}`" if result.get("low_level") == "learned" else "") + ".\n"
    )


def pipeline_phases(cfg: DictConfig) -> tuple[list[dict], Path | None]:
    """A pipeline folder's finished phases (up to ``cfg.phase`` if set) and that phase's
    checkpoint; ``[]`` and ``None`` for anything else."""
    phases = load_state(Path(str(cfg.checkpoint)))
    if cfg.phase is None:
        return phases, None
    names = [p["name"] for p in phases]
    if cfg.phase not in names:
        raise ValueError(f"phase={cfg.phase!r} is not a finished phase of checkpoint={cfg.checkpoint!r} "
                         f"(finished: {names}; a pipeline folder is needed)")
    phases = phases[: names.index(cfg.phase) + 1]
    return phases, Path(phases[-1]["checkpoint"])


def pipeline_costs(folder: Path, phases: list[dict]) -> dict:
    """What a pipeline's training cost (wall time, frames, MuJoCo's frames) and how it was
    launched: from random weights, from an empty folder, on which commits."""
    def backend(phase: dict) -> str:  # phases recorded before 2026-12-03 lack it: their checkpoint has it
        return phase.get("backend") or load_checkpoint(Path(phase["checkpoint"]))["cfg"]["env"]["backend"]

    launches = load_launches(folder)
    first = load_checkpoint(Path(phases[0]["checkpoint"]))["cfg"]
    return {"from_scratch": first.get("warm_start") is None, "phases": phases,
            "train_wall_s": sum(p["wall_s"] for p in phases), "env_frames": sum(p["frames"] for p in phases),
            "mujoco_frames": sum(p["frames"] for p in phases if backend(p) == "mujoco"),
            "pipeline_launches": launches,
            # Not recorded by folders older than the launch records: unknown, not assumed.
            "from_empty_folder": (launches[0]["folder_was_empty"] and not launches[0]["branch_from"]) if launches else None,
            "launch_commits": sorted({entry["commit"] for entry in launches})}


def observation_noise(cfg: DictConfig, env) -> dict | None:
    """The student's noise model on the policy's own observation when ``noise_scale`` or
    ``dropout_p`` is set (``pnp.distill.student.add_observation_noise``); None: clean."""
    if cfg.noise_scale is None and cfg.dropout_p is None:
        return None
    return add_observation_noise(env, resolve_seed(cfg.seed), cfg.noise_scale, cfg.dropout_p)


def displacement_settings(cfg: DictConfig) -> dict:
    """``cfg.displacement`` with its clearance default filled in."""
    settings = {"delay_s": DELAY_S, "distance": list(DISTANCE_M), "clearance": CLEARANCE_M}
    unknown = set(cfg.displacement) - set(settings)
    if unknown:
        raise ValueError(f"displacement: unknown keys {sorted(unknown)}; known: {sorted(settings)}")
    given = OmegaConf.to_container(cfg.displacement, resolve=True)
    settings.update({k: v for k, v in given.items() if v is not None})
    return settings


def displacement_hook(cfg: DictConfig, num_worlds: int) -> BoxDisplacement | None:
    """The box moved once per episode after its first lift (``pnp.studies.recovery``); None: never."""
    if cfg.displacement is None:
        return None
    return BoxDisplacement(num_worlds, resolve_seed(cfg.seed), **displacement_settings(cfg))


def evaluate(cfg: DictConfig) -> dict:
    phases, ckpt_path = pipeline_phases(cfg)
    selection = Path(str(cfg.checkpoint)) / SELECTION if cfg.selected else None
    if selection is not None:
        if cfg.phase is not None:
            raise ValueError(f"selected=true judges the selection's choice; phase={cfg.phase!r} names another checkpoint")
        ckpt_path = selected_checkpoint(selection.parent)
    ckpt_path = ckpt_path or resolve_checkpoint(cfg.checkpoint, cfg.runs_root)
    check_clean(cfg.out, cfg.dirty_reason)
    t0 = time.monotonic()
    sample = check_groups(cfg.sample)
    seed = resolve_seed(cfg.seed)
    overrides = {k: v for k, v in cfg.env.items() if k != "num_worlds"}
    num_worlds = min(int(cfg.env.num_worlds), int(cfg.trials))
    pol = load_policy(ckpt_path, num_worlds, seed, **overrides)
    noise = observation_noise(cfg, pol.env)
    records = run_trials(pol.env, pol.actor, int(cfg.trials), bool(cfg.progress), sample,
                         hook=displacement_hook(cfg, num_worlds))
    pol.env.close()
    env, counters, trained = pol.cfg.env, pol.ckpt["counters"], pol.cfg
    result = {
        "backend": env.backend, "num_robots": int(env.num_robots), "num_worlds": int(env.num_worlds),
        "start_range_m": [float(x) for x in env.start_range],
        "max_episode_s": seconds(env.max_episode_steps or round(EPISODE_S / HL_DT)),
        **summarise(records), "checkpoint": str(ckpt_path),
        "checkpoint_iteration": int(counters["iteration"]), "checkpoint_frames": int(counters["frames"]),
        # This run's training (a warm-started run's source trained before: see warm_started_from).
        "env_steps": int(counters["frames"]), "train_wall_s": float(counters["wall_s"]),
        "warm_started_from": trained.warm_start, "trained_backend": pol.ckpt["cfg"]["env"]["backend"],
        "training_launches": pol.ckpt.get("launches", []),
        "folded_inputs": pol.folded, "sampled_actions": list(sample),
        "schedule": trained.curriculum.schedule if trained.curriculum.stage_rewards else "none", "train_seed": int(trained.seed),
        "low_level": env.low_level, "observation_noise": noise,
        "low_level_checkpoint": str(resolve_checkpoint(env.low_level_checkpoint, cfg.runs_root)) if env.low_level == "learned" else None,
        # Per trial (trial, success, steps, cause): any later evaluation on this seed pairs with it.
        "trial_records": trial_table(records), **evaluation_record(pol.ckpt, seed, cfg.dirty_reason),
    }
    if cfg.displacement is not None:  # the box moved once per episode: recovery figures beside the rest
        result["displacement"] = {"settings": displacement_settings(cfg),
                                  **{k: v for k, v in recovery_summary(records).items() if k != "records"}}
    comparison = None
    if cfg.compare is not None:  # a second policy on the same trials
        other = load_policy(resolve_checkpoint(cfg.compare, cfg.runs_root), num_worlds, seed, **overrides)
        observation_noise(cfg, other.env)
        other_records = run_trials(other.env, other.actor, int(cfg.trials), bool(cfg.progress), sample,
                                   hook=displacement_hook(cfg, num_worlds))
        other.env.close()
        comparison = paired_comparison(records, other_records)
        result["comparison"] = {"checkpoint_b": str(cfg.compare), **summarise(other_records), **comparison}
    result["wall_s"] = time.monotonic() - t0
    if selection is not None:
        result["selection"] = str(selection)
    if phases:  # a pipeline folder: every phase's cost
        result.update(pipeline_costs(Path(str(cfg.checkpoint)), phases))
    out = Path(cfg.out) if cfg.out else ckpt_path.parent / f"eval_{env.backend}.json"
    method = cfg.method or f"Ours ({result['schedule']} curriculum, {result['backend']})" + (
        f", sampled {'+'.join(sample)}" if sample else "")
    markdown = table_md(result, method)
    if comparison is not None:
        markdown += "\n" + comparison_md(comparison, "this checkpoint", f"`{cfg.compare}`")
    return write_result(result, out, markdown)
