"""The paper's recovery claim, measured: a distilled student and its teacher when the box is
moved away after the lift, and under long mocap dropouts (deterministic policies).

    python recipes/student_recovery.py checkpoint=runs/distill_single out=results/student_recovery.json
    python recipes/student_recovery.py checkpoint=runs/distill_dual trials=50 env.num_worlds=50

Two comparisons in evaluation envs built alike (paper layouts, 45 s, ending at success;
seeded by ``seed``, the same for every policy), ``trials`` each:

* ``displacement``: 1 s after the box is first lifted it is moved 0.5-1 m in a random
  direction and set down at rest, released (``pnp.studies.recovery.BoxDisplacement``);
  the student on its noisy observation, the teacher with the same noise, the teacher on
  clean observations. Success, completion time, and per trial whether the policy grasped
  and lifted the box again, with its stage history after the displacement.
* ``dropout``: the object pose frozen for 0.5-2 s at random times (the student's noise
  model with frequent dropouts), the student against the noisy teacher.

Writes one JSON file with both comparisons, the settings and the provenance, and a markdown
table beside it (default: ``<run>/student_recovery_<backend>.json|md``).
"""
from __future__ import annotations

import time
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from pnp.task import EPISODE_S, HL_DT
from pnp.training.checkpoint import resolve_checkpoint
from pnp.training.collect import seconds
from pnp.training.protocol import resolve_seed
from pnp.training.provenance import check_clean, evaluation_record, write_result
from pnp.studies.recovery import CLEARANCE_M, evaluate_recovery

LABELS = {"student": "Student (noisy observations)", "teacher_noisy": "Teacher (same noise)",
          "teacher_clean": "Teacher (clean observations)"}


def _pct(x) -> str:
    return "-" if x is None else f"{100 * x:.1f}"


def _time(mean, std) -> str:
    return "-" if mean is None else f"{mean:.2f} ± {std:.2f}"


def table_md(result: dict) -> str:
    d, p = result["displacement_settings"], result["dropout_settings"]
    header = ("| Policy | Success (%) | Displaced | Recovered (% of displaced) | Re-grasped (%) | Re-lifted (%) | "
              "Completion time (s) | Displacement to success (s) |")
    rows = [header, "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for name, r in result["displacement"].items():
        rows.append(f"| {LABELS[name]} | {_pct(r['success_rate'])} | {r['displaced']} | {_pct(r['recovery_rate'])} | "
                    f"{_pct(r['regrasp_rate'])} | {_pct(r['relift_rate'])} | "
                    f"{_time(r['completion_time_mean_s'], r['completion_time_std_s'])} | "
                    f"{_time(r['recovery_time_mean_s'], r['recovery_time_std_s'])} |")
    moved = (f"Box moved {d['distance'][0]}-{d['distance'][1]} m and set down at rest {d['delay_s']} s after its "
             "first lift, once per episode.")
    rows += ["", moved, "", "| Policy | Success (%) | Completion time (s) |", "| --- | --- | --- |"]
    for name, r in result["dropout"].items():
        rows.append(f"| {LABELS[name]} | {_pct(r['success_rate'])} | "
                    f"{_time(r['completion_time_mean_s'], r['completion_time_std_s'])} |")
    frozen = (f"Object pose frozen for {p['min_s']}-{p['max_s']} s, a dropout starting after a seen step with "
              f"probability {p['p']}.")
    where = (f"{result['trials']} trials per policy on the {result['backend']} backend, {result['num_robots']} "
             f"robot(s), seed {result['seed']} ({result['seed_role']}). Student `{result['checkpoint']}` (iteration "
             f"{result['checkpoint_iteration']}), teacher `{result['teacher']}`.")
    rows += ["", frozen, "", where]
    return "\n".join(rows) + "\n"


def evaluate(cfg: DictConfig) -> dict:
    ckpt_path = resolve_checkpoint(cfg.checkpoint, cfg.runs_root)
    check_clean(cfg.out, cfg.dirty_reason)
    t0, seed = time.monotonic(), resolve_seed(cfg.seed)
    displacement = OmegaConf.to_container(cfg.displacement)
    if displacement["clearance"] is None:
        displacement["clearance"] = CLEARANCE_M
    dropout = OmegaConf.to_container(cfg.dropout)
    overrides = {k: v for k, v in cfg.env.items() if k != "num_worlds"}
    num_worlds = min(int(cfg.env.num_worlds), int(cfg.trials))
    ecfg, ckpt, runs = evaluate_recovery(ckpt_path, int(cfg.trials), num_worlds, seed, displacement, dropout,
                                         bool(cfg.progress), **overrides)
    env, counters = ecfg.env, ckpt["counters"]
    result = {
        "backend": env.backend, "num_robots": int(env.num_robots), "num_worlds": int(env.num_worlds),
        "start_range_m": [float(x) for x in env.start_range],
        "max_episode_s": seconds(env.max_episode_steps or round(EPISODE_S / HL_DT)), "trials": int(cfg.trials),
        "displacement_settings": displacement, "dropout_settings": dropout, **runs,
        "noise": OmegaConf.to_container(ecfg.noise), "student_observation": OmegaConf.to_container(ecfg.student),
        # Layouts and displacement directions paired across policies; the noise is drawn per run.
        "checkpoint": str(ckpt_path), "checkpoint_iteration": int(counters["iteration"]),
        "env_steps": int(counters["frames"]), "teacher": str(ecfg.distill.teacher),
        "trained_backend": ckpt["cfg"]["env"]["backend"], "training_launches": ckpt.get("launches", []),
        "wall_s": time.monotonic() - t0, **evaluation_record(ckpt, seed, cfg.dirty_reason),
    }
    out = Path(cfg.out) if cfg.out else ckpt_path.parent / f"student_recovery_{env.backend}.json"
    return write_result(result, out, table_md(result))
