"""The paper's curriculum ablation: 4-stage EE tracking, dynamic vs Liu et al. (max) and (min).

    python recipes/ablation_ee.py                          # 4 methods x 3 seeds, 1000 iterations each
    python recipes/ablation_ee.py seeds=[0] iterations=50  # a quicker look

Every run trains ``recipes/train.py`` on ``env.task=ee_tracking`` with the same budget
(``iterations`` x ``collect.frames_per_batch`` frames) into ``runs_dir/<method>_s<seed>``;
an existing run resumes (or is skipped when complete; a larger ``iterations`` trains it on),
so the ablation survives restarts. Each finished run's result and curve rows are also kept
in ``records_dir`` (committed), so finished runs survive the loss of ``runs_dir`` too. A
method is a schedule (``schedules``) or a named variant (``variants``: a schedule plus
overrides, e.g. ``curriculum.completed_floor``).
Then each policy runs ``eval_trials`` episodes, deterministic and with sampled actions. Writes ``out`` (JSON: per
method and seed the first iteration at which most episodes end in S4, the final success
rate, the mean completion time and the budget used) and, beside it, PNGs of success rate,
completion time and mean end-of-episode stage vs iteration (mean over seeds, min-max band),
and of each method's reward scales rho_j, each over its largest value (first seed), which
explain where a schedule stalls.
"""
from __future__ import annotations

import json
import math
import time
import warnings
from pathlib import Path

import matplotlib
import numpy as np
import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import DictConfig

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from pnp.training.choices import RECIPES_CONFIG  # noqa: E402
from pnp.training.config import register  # noqa: E402
from pnp.training.plots import load_metrics  # noqa: E402
from pnp.training.provenance import provenance  # noqa: E402
from pnp.training.rollout import load_policy, run_trials, summarise  # noqa: E402
from pnp.studies.run_records import compact, reuse_or_finish  # noqa: E402
from pnp.training.tasks import schedule_of  # noqa: E402
from pnp.training.trainer import train  # noqa: E402

register()

# The metric columns a record keeps for the curves (the thresholds are computed from every column first).
ROW_KEYS = ("iteration", "frames", "wall_s", "episodes", "success_rate", "completion_time_s", "mean_end_stage")
ROW_PREFIXES = ("stage_share/", "rho/")
CURVES = {"success_rate": "success rate", "completion_time_s": "completion time (s)",
          "mean_end_stage": "mean end-of-episode stage"}


def methods(cfg: DictConfig) -> dict[str, list[str]]:
    """Each method's overrides: a schedule alone, or a variant's schedule plus its overrides."""
    out = {schedule: [f"curriculum.schedule={schedule}"] for schedule in cfg.schedules}
    for name, variant in (cfg.variants or {}).items():
        if variant is None:  # dropped from the command line: variants.<name>=null
            continue
        if name in out or set(variant) != {"schedule", "overrides"}:
            raise ValueError(f"variants.{name}: needs a new name and exactly the keys schedule, overrides; got {dict(variant)}")
        out[name] = [f"curriculum.schedule={variant.schedule}", *variant.overrides]
    return out


def train_config(cfg: DictConfig, method: str, overrides: list[str], seed: int) -> DictConfig:
    run = Path(cfg.runs_dir) / f"{method}_s{seed}"
    overrides = [*cfg.train, *overrides, f"seed={seed}", f"out_dir={run}", f"total_iterations={int(cfg.iterations)}"]
    if (run / "checkpoint.pt").is_file():
        overrides.append(f"resume={run}")
    if GlobalHydra.instance().is_initialized():  # under @hydra.main: same config folder
        return compose("train", overrides=overrides)
    with initialize_config_dir(config_dir=RECIPES_CONFIG, version_base="1.3"):
        return compose("train", overrides=overrides)


def evaluate_policy(run: Path, trials: int, seed: int) -> dict:
    """``trials`` deterministic episodes: success rate, completion time (s) of the successes and
    mean end stage; under "sampled" the same trials with actions drawn from the policy, as it
    trained: with the 0.3 std floor the mean action is another policy (probe E6 at 1000
    iterations, seed 777: S4 in 37 % deterministic, 82 % sampled)."""
    keys = ("trials", "success_rate", "completion_time_mean_s", "completion_time_std_s", "mean_end_stage")
    out = {}
    for sample in (None, ["all"]):
        torch.manual_seed(seed)  # the draws of the sampled trials
        pol = load_policy(run / "checkpoint.pt", trials, seed)
        summary = summarise(run_trials(pol.env, pol.actor, trials, sample=sample),
                            n_stages=schedule_of(pol.env).n_stages)
        pol.env.close()
        out.update({k: summary[k] for k in keys} if sample is None else {"sampled": {k: summary[k] for k in keys}})
    return out


def first_majority_in_final(rows: list[dict]) -> int | None:
    """First iteration at which more than half of the episodes that ended, ended in S4."""
    return first_majority_at_least(rows, 4)


def first_majority_at_least(rows: list[dict], k: int) -> int | None:
    """First iteration at which more than half of the episodes that ended, ended in S_k or later."""
    def share(r):
        return sum(v for key, v in r.items() if key.startswith("stage_share/S") and int(key[13:]) >= k
                   and math.isfinite(v))
    return next((r["iteration"] for r in rows if r.get("episodes", 0) > 0 and share(r) > 0.5), None)


def final_mean(rows: list[dict], key: str, frac: float = 0.1) -> float | None:
    """Episode-weighted mean of ``key`` over the last ``frac`` of the iterations."""
    last = max(r["iteration"] for r in rows)
    tail = [r for r in rows if r["iteration"] > (1 - frac) * last and r.get("episodes", 0) > 0
            and math.isfinite(r.get(key, math.nan))]
    n = sum(r["episodes"] for r in tail)
    return sum(r[key] * r["episodes"] for r in tail) / n if n else None


def windowed(rows: list[dict], key: str, window: int) -> tuple[np.ndarray, np.ndarray]:
    """Episode-weighted means of ``key`` over windows of iterations (NaN where none ended)."""
    last = max(r["iteration"] for r in rows)
    edges = np.arange(0, last + window, window)
    sums, counts = np.zeros(len(edges)), np.zeros(len(edges))
    for r in rows:
        v, n = r.get(key, math.nan), r.get("episodes", 0.0)
        if key == "completion_time_s":
            n = n * r.get("success_rate", 0.0)  # averaged over successful episodes
        if n > 0 and math.isfinite(v):
            i = (r["iteration"] - 1) // window
            sums[i] += v * n
            counts[i] += n
    with np.errstate(invalid="ignore"):
        return edges + window, np.where(counts > 0, sums / np.maximum(counts, 1e-12), np.nan)


def plot_curves(runs: dict[str, dict[int, list[dict]]], window: int, out_dir: Path) -> list[Path]:
    written = []
    for key, label in CURVES.items():
        fig, ax = plt.subplots(figsize=(6, 3.5))
        for method, by_seed in runs.items():
            curves = [windowed(rows, key, window) for rows in by_seed.values() if rows]
            if not curves:
                continue
            n = min(len(c[0]) for c in curves)
            x, ys = curves[0][0][:n], np.stack([c[1][:n] for c in curves])
            with warnings.catch_warnings():  # all-NaN windows (no episode ended) stay NaN
                warnings.simplefilter("ignore", RuntimeWarning)
                mean, lo, hi = np.nanmean(ys, 0), np.nanmin(ys, 0), np.nanmax(ys, 0)
            (line,) = ax.plot(x, mean, label=f"{method} ({len(curves)} seeds)")
            ax.fill_between(x, lo, hi, color=line.get_color(), alpha=0.2)
        ax.set(xlabel="iteration", ylabel=label)
        ax.grid(alpha=0.3)
        ax.legend()
        fig.tight_layout()
        path = out_dir / f"ablation_ee_{key}.png"
        fig.savefig(path, dpi=120)
        plt.close(fig)
        written.append(path)
    return written


def plot_rho(runs: dict[str, dict[int, list[dict]]], out_dir: Path) -> Path:
    """rho_j of every stage term vs iteration on a log scale (mu_j and the K-divided values
    apart by decades), one panel per method with a rho state (its first seed; Liu et al.'s
    coefficients follow each step's stage, no state)."""
    def has_rho(by_seed):
        return any(k.startswith("rho/") for r in next(iter(by_seed.values())) for k in r)

    runs = {m: s for m, s in runs.items() if has_rho(s)} or runs
    fig, axes = plt.subplots(1, len(runs), figsize=(3.6 * len(runs), 3.2), sharey=True, squeeze=False)
    for ax, (method, by_seed) in zip(axes[0], runs.items()):
        rows = next(iter(by_seed.values()))
        for key in sorted({k for r in rows for k in r if k.startswith("rho/")}):
            values = np.array([r.get(key, math.nan) for r in rows])
            ax.plot([r["iteration"] for r in rows], values, label=key[4:])
        ax.set_yscale("symlog", linthresh=1e-2)  # linear near 0: a rho of 0 still plots
        ax.set(title=f"{method} (seed {next(iter(by_seed))})", xlabel="iteration")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("rho_j")
    axes[0][-1].legend(fontsize=7)
    fig.tight_layout()
    path = out_dir / "ablation_ee_rho.png"
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def run_seed(cfg: DictConfig, method: str, overrides: list[str], seed: int) -> tuple[dict, list[dict], str]:
    """One run's result, its curve rows and its backend: from its record in ``records_dir``
    while that holds the run's settings and budget, else trained (or resumed) and evaluated."""
    tcfg = train_config(cfg, method, overrides, seed)
    path = Path(cfg.records_dir) / f"{method}_s{seed}.json"
    settings = {"eval_trials": int(cfg.eval_trials), "eval_seed": int(cfg.eval_seed)}
    kept = reuse_or_finish(path, tcfg, settings, lambda: finish_run(tcfg, settings, f"{method} seed {seed}"),
                           holds=lambda k: k["result"]["budget"]["iterations"] == int(cfg.iterations))
    return kept["result"], kept["rows"], str(tcfg.env.backend)


def finish_run(tcfg: DictConfig, settings: dict, label: str) -> dict:
    """Train (or resume) the run of ``tcfg`` and evaluate it: the payload of its record."""
    if train(tcfg)["stopped_by_signal"]:
        # The run checkpointed; stop here too (a caller sent SIGTERM/SIGINT), or this
        # process would go on writing into the next runs' folders.
        raise SystemExit(f"stopped by a signal during {label}; rerun to resume")
    run = Path(tcfg.out_dir)
    rows = load_metrics(run / "metrics.jsonl")
    last = rows[-1] if rows else {}
    result = {
        "iterations_to_S4_majority": first_majority_in_final(rows),
        "iterations_to_majority_at_least": {f"S{k}": first_majority_at_least(rows, k) for k in range(1, 5)},
        "final_mean_end_stage_train": final_mean(rows, "mean_end_stage"),
        **evaluate_policy(run, settings["eval_trials"], settings["eval_seed"]),
        "budget": {"iterations": last.get("iteration"), "frames": last.get("frames"),
                   "train_wall_s": last.get("wall_s")},
        "run": str(run),
    }
    return {"result": result, "rows": compact(rows, ROW_KEYS, ROW_PREFIXES, digits=4),
            "eval_settings": settings, "finished": provenance()}


def run_ablation(cfg: DictConfig) -> dict:
    out = Path(cfg.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    t0, prov = time.monotonic(), provenance()  # before any output: the tree is still clean
    results, curves, backend, by_name = {}, {}, None, methods(cfg)
    for method, overrides in by_name.items():
        results[method], curves[method] = {}, {}
        for seed in cfg.seeds:
            result, rows, backend = run_seed(cfg, method, overrides, int(seed))
            results[method][f"seed_{seed}"], curves[method][int(seed)] = result, rows
    pngs = plot_curves(curves, int(cfg.window), out.parent) + [plot_rho(curves, out.parent)]
    summary = {m: _summary(r) for m, r in results.items()}
    train_wall = sum(r["budget"]["train_wall_s"] or 0.0 for by_seed in results.values() for r in by_seed.values())
    doc = {"task": "ee_tracking (4 points)", "backend": backend, "methods": by_name, "results": results, "summary": summary,
           "plots": [str(p) for p in pngs], "train_wall_s_total": train_wall, "wall_s": time.monotonic() - t0, **prov}
    out.write_text(json.dumps(doc, indent=2) + "\n")
    return doc


def _summary(by_seed: dict) -> dict:
    def stat(key, group=None):  # records written before 2026-12-05 lack the mean end stage and "sampled"
        vals = [v for r in by_seed.values() if (v := (r.get(group) or {} if group else r).get(key)) is not None]
        return {"mean": float(np.mean(vals)), "std": float(np.std(vals)), "n": len(vals)} if vals else None

    out = {k: stat(k) for k in ("iterations_to_S4_majority", "final_mean_end_stage_train", "success_rate",
                                "completion_time_mean_s", "mean_end_stage")}
    out["sampled"] = {k: stat(k, "sampled") for k in ("success_rate", "completion_time_mean_s", "mean_end_stage")}
    return out
