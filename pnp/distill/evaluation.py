"""Evaluate a distilled student beside its teacher over N trials each (deterministic policies).

    python recipes/evaluate_student.py checkpoint=runs/distill_single out=results/eval_student_single.json
    python recipes/evaluate_student.py checkpoint=runs/distill_dual trials=100 env.num_worlds=100

Three runs in evaluation envs built alike (paper layouts, 45 s, ending at success; seeded
by ``seed``): ``student`` on its noisy observation, ``teacher_noisy`` with the same noise
model on its own observation layout (stage from the simulator), and ``teacher_clean``, the
reference. Writes one JSON file with the three ``summarise`` figures (success rate,
completion time, failure causes, stages), the noise model and the provenance, and a
markdown table beside it (default: ``<run>/eval_student_<backend>.json|md``). The top-level
``success_rate`` and completion times are the student's. ``noise_scale=0 dropout_p=0`` runs
all three on exact observations: how much of a student's gap to its teacher the noise is.
"""
from __future__ import annotations

import time
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from pnp.task import EPISODE_S, HL_DT
from pnp.training.checkpoint import resolve_checkpoint
from pnp.training.collect import seconds
from pnp.training.paired import comparison_md, paired_comparison, trial_table
from pnp.training.protocol import resolve_seed
from pnp.training.provenance import check_clean, evaluation_record, write_result
from pnp.training.rollout import summarise
from pnp.distill.student import evaluate_views

LABELS = {"student": "Student (noisy observations)", "teacher_noisy": "Teacher (same noise)",
          "teacher_clean": "Teacher (clean observations)"}


def table_md(result: dict) -> str:
    rows = []
    for name, label in LABELS.items():
        r = result[name]
        t = r["completion_time_mean_s"]
        time_s = "-" if t is None else f"{t:.2f} ± {r['completion_time_std_s']:.2f}"
        rows.append(f"| {label} | {100 * r['success_rate']:.1f} | {time_s} |")
    return ("| Policy | Success rate (%) | Completion time (s) |\n| --- | --- | --- |\n" + "\n".join(rows) +
            f"\n\n{result['trials']} trials each on the {result['backend']} backend, {result['num_robots']} "
            f"robot(s), seed {result['seed']} ({result['seed_role']}), the same trials for each. Student `{result['checkpoint']}` (iteration "
            f"{result['checkpoint_iteration']}), teacher `{result['teacher']}`.\n")


def evaluate(cfg: DictConfig) -> dict:
    ckpt_path = resolve_checkpoint(cfg.checkpoint, cfg.runs_root)
    check_clean(cfg.out, cfg.dirty_reason)
    t0, seed = time.monotonic(), resolve_seed(cfg.seed)
    overrides = {k: v for k, v in cfg.env.items() if k != "num_worlds"}
    num_worlds = min(int(cfg.env.num_worlds), int(cfg.trials))
    ecfg, ckpt, records = evaluate_views(ckpt_path, int(cfg.trials), num_worlds, seed, bool(cfg.progress),
                                      cfg.noise_scale, cfg.dropout_p, **overrides)
    runs = {name: summarise(r) for name, r in records.items()}
    env, counters, student = ecfg.env, ckpt["counters"], runs["student"]
    # Same layouts for all three (paired trials); the observation noise is drawn per run.
    comparisons = {f"student_vs_{t}": paired_comparison(records["student"], records[t]) for t in ("teacher_noisy", "teacher_clean")}
    result = {
        "backend": env.backend, "num_robots": int(env.num_robots), "num_worlds": int(env.num_worlds),
        "start_range_m": [float(x) for x in env.start_range],
        "max_episode_s": seconds(env.max_episode_steps or round(EPISODE_S / HL_DT)),
        "trials": student["trials"], "success_rate": student["success_rate"],
        "completion_time_mean_s": student["completion_time_mean_s"],
        "completion_time_std_s": student["completion_time_std_s"], **runs,
        "noise": OmegaConf.to_container(ecfg.noise), "student_observation": OmegaConf.to_container(ecfg.student),
        "comparisons": comparisons, "trial_records": {n: trial_table(r) for n, r in records.items()},
        "checkpoint": str(ckpt_path), "checkpoint_iteration": int(counters["iteration"]),
        "env_steps": int(counters["frames"]), "train_wall_s": float(counters["wall_s"]),
        "teacher": str(ecfg.distill.teacher), "beta": float(ecfg.distill.beta),
        "direction": str(ecfg.distill.direction), "trained_backend": ckpt["cfg"]["env"]["backend"],
        "training_launches": ckpt.get("launches", []),
        "wall_s": time.monotonic() - t0, **evaluation_record(ckpt, seed, cfg.dirty_reason),
    }
    out = Path(cfg.out) if cfg.out else ckpt_path.parent / f"eval_student_{env.backend}.json"
    markdown = table_md(result) + "".join(
        "\n" + comparison_md(c, "student", k.split("_vs_")[1]) for k, c in comparisons.items())
    return write_result(result, out, markdown)
