"""The comparison with the paper's baselines: Table I, Fig. 6 and the training-efficiency claim.

    python recipes/table1.py                               # 5 methods x 3 seeds, then 500 MuJoCo trials each
    python recipes/table1.py methods=[dynamic,bendikas] seeds=[0]   # a subset

Every method trains ``experiment=table1_<method>`` (the same phases and frame budget,
``recipes/config/experiment/table1_common.yaml``) with each seed into
``runs_dir/<method>_s<seed>``, one training at a time, seed by seed (every method's seed 0
first); a stopped run resumes (the pipeline's own resume). Every seed runs the kinematic
phases (those before the first MuJoCo phase); the seeds in ``mujoco_seeds`` go on through
the MuJoCo phases, since a MuJoCo fine-tune that learns costs about an hour here. Each
seed's kinematic policy runs ``eval_kinematic.trials`` deterministic episodes and each MuJoCo
seed's final policy ``eval.trials`` (Table I). A finished run's record (rows, evaluations)
goes to ``records_dir`` and is reused while its settings hold, so the comparison survives a
lost ``runs_dir`` across sessions (``pnp.studies.run_records``). Writes ``out``: per method and
seed the frames and wall time until the training mean end stage and success rate reach
their thresholds over the kinematic phases (null if never), the evaluations, and the ratios
against the best baseline; and beside it PNGs of the mean end-of-episode stage (paper Fig. 6)
and the training success rate vs frames over the kinematic phases, mean over seeds with
their min-max band.

Bendikas et al.'s sub-tasks before the last end their episodes at S_{k+1} and count that as
success: their iterations are left out of the thresholds and of the success curve (the
stage curve shows them: its staircase is the sub-task sequence).
"""
from __future__ import annotations

import json
import math
import time
import warnings
from pathlib import Path

import matplotlib
import numpy as np
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import DictConfig, OmegaConf

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from pnp.task.terms import STAGES  # noqa: E402
from pnp.training.collect import windowed_mean  # noqa: E402
from pnp.training.choices import RECIPES_CONFIG  # noqa: E402
from pnp.training.config import register  # noqa: E402
from pnp.training.pipeline import load_state, phase_dir, pipeline_phases, run_pipeline, total_frames  # noqa: E402
from pnp.training.plots import load_metrics  # noqa: E402
from pnp.training.provenance import provenance  # noqa: E402
from pnp.training.rollout import load_policy, run_trials, summarise  # noqa: E402
from pnp.studies.run_records import compact, reuse_or_finish  # noqa: E402
from pnp.training.stage_ensemble import parameter_count  # noqa: E402
from pnp.studies.table1_report import markdown  # noqa: E402
from pnp.studies.ratio_ci import table1_intervals  # noqa: E402
from pnp.studies.table1_tuning import AS_BUILT, check_tuning, run_name, tune, with_candidate  # noqa: E402
from pnp.training.trainer import make_training  # noqa: E402

register()

LAST_SUBTASK = len(STAGES) - 1
LABELS = {"mean_end_stage": "stage", "success_rate": "success"}
CURVES = {"end_stage": "mean end-of-episode stage", "success_rate": "training success rate (full task)"}
EXITS = {1: "success", 2: "frames"}  # pnp.baselines.bendikas's subtask_exit codes


def _compose(overrides: list[str]) -> DictConfig:
    if GlobalHydra.instance().is_initialized():  # under @hydra.main: same config folder
        return compose("train", overrides=overrides)
    with initialize_config_dir(config_dir=RECIPES_CONFIG, version_base="1.3"):
        return compose("train", overrides=overrides)


def kinematic_phases(tcfg: DictConfig) -> list[str]:
    """The pipeline's phases before its first MuJoCo phase (all of them if it has none)."""
    names = []
    for name, phase in pipeline_phases(tcfg):
        if phase.overrides.get("env.backend", tcfg.env.backend) == "mujoco":
            break
        names.append(name)
    if not names:
        raise ValueError(f"experiment pipeline {list(tcfg.pipeline)} starts on MuJoCo: the comparison needs kinematic phases first")
    return names


def train_config(cfg: DictConfig, method: str, seed: int, candidate: str = AS_BUILT) -> tuple[DictConfig, DictConfig]:
    """The run's config (the kinematic phases only unless ``seed`` is in ``cfg.mujoco_seeds``)
    and the full pipeline's (for the budget), with the tuning ``candidate``'s overrides."""
    run = Path(cfg.runs_dir) / run_name(method, candidate, seed)
    overrides = [f"experiment=table1_{method}", *cfg.train, f"seed={seed}", f"out_dir={run}"]
    full = with_candidate(_compose(overrides), cfg.tuning.candidates, candidate)
    if seed in cfg.mujoco_seeds:
        return full, full
    kinematic = full.copy()
    kinematic.pipeline = kinematic_phases(full)
    return kinematic, full


def budget_frames(tcfg: DictConfig) -> int:
    if not tcfg.pipeline:
        raise ValueError("experiment=table1_<method> must declare a pipeline (its phases and frame budget)")
    return total_frames(tcfg)


def run_rows(run: Path) -> list[dict]:
    """Every phase's metric rows on one axis: frames and wall time cumulative over the
    phases; ``end_stage`` the stage episodes end in whatever the phase's reading."""
    rows, frames, wall = [], 0, 0.0
    for i, phase in enumerate(load_state(run)):
        for r in load_metrics(phase_dir(run, i, phase["name"]) / "metrics.jsonl"):
            rows.append({**r, "frames": frames + r["frames"], "wall_s": wall + r["wall_s"], "phase": phase["name"],
                         "end_stage": r.get("mean_final_stage", r["mean_end_stage"])})
        frames, wall = frames + phase["frames"], wall + phase["wall_s"]
    return rows


def full_task(rows: list[dict]) -> list[dict]:
    """Rows whose episodes are the whole task (all but Bendikas' earlier sub-tasks)."""
    return [r for r in rows if r.get("subtask", LAST_SUBTASK) == LAST_SUBTASK]


def first_reaching(rows: list[dict], key: str, threshold: float, window: int) -> dict | None:
    """The first row at which ``key``'s episode-weighted mean over the last ``window`` rows reaches ``threshold``."""
    for i in range(window, len(rows) + 1):
        value = windowed_mean(rows[:i], key, window)
        if value is not None and value >= threshold:
            return rows[i - 1]
    return None


def label(metric: str, threshold: float) -> str:
    """``mean_end_stage``, 5.5 -> ``stage_5_5`` (the JSON key's suffix)."""
    if metric not in LABELS:
        raise ValueError(f"thresholds: unknown metric {metric!r}; choose from {sorted(LABELS)}")
    return f"{LABELS[metric]}_{threshold:g}".replace(".", "_")


def efficiency(rows: list[dict], thresholds: DictConfig, window: int) -> dict:
    out, task = {}, full_task(rows)
    for metric, threshold in thresholds.items():
        row = first_reaching(task, "end_stage" if metric == "mean_end_stage" else metric, float(threshold), window)
        name = label(metric, float(threshold))
        out[f"frames_to_{name}"] = None if row is None else int(row["frames"])
        out[f"wall_s_to_{name}"] = None if row is None else float(row["wall_s"])
    return out


def subtask_history(rows: list[dict]) -> list[dict]:
    """Bendikas' sub-task ends: which, how (success threshold or frame cap), at what frame count."""
    return [{"subtask": int(r["subtask"]), "exit": EXITS[int(r["subtask_exit"])], "frames": int(r["frames"])}
            for r in rows if r.get("subtask_exit", 0) > 0]


def phase_checkpoint(run: Path, name: str) -> Path:
    phases = load_state(run)
    index = [p["name"] for p in phases].index(name)
    return phase_dir(run, index, name) / "checkpoint.pt"


def evaluate(ckpt: Path, ecfg: DictConfig) -> dict:
    """``ckpt`` over ``ecfg.trials`` deterministic episodes (kept in the run's record, not cached apart)."""
    overrides = {k: ecfg[k] for k in ("backend", "nthread", "start_range", "max_episode_steps")}
    pol = load_policy(ckpt, min(int(ecfg.num_worlds), int(ecfg.trials)), int(ecfg.seed), **overrides)
    t0 = time.monotonic()
    summary = summarise(run_trials(pol.env, pol.actor, int(ecfg.trials)))
    pol.env.close()
    keep = ("trials", "success_rate", "completion_time_mean_s", "completion_time_std_s", "failure_causes",
            "mean_end_stage")
    return {**{k: summary[k] for k in keep}, "eval_wall_s": time.monotonic() - t0}


def pooled_times(evals: list[dict]) -> tuple[float | None, float | None]:
    """Mean and population std of the completion times of all successful trials of all seeds."""
    parts = [(round(e["success_rate"] * e["trials"]), e["completion_time_mean_s"], e["completion_time_std_s"])
             for e in evals if e["completion_time_mean_s"] is not None]
    n = sum(p[0] for p in parts)
    if not n:
        return None, None
    mean = sum(k * m for k, m, _ in parts) / n
    var = sum(k * (s * s + m * m) for k, m, s in parts) / n - mean * mean
    return mean, math.sqrt(max(var, 0.0))


def method_mean(seeds: dict, key: str) -> float | None:
    """Mean over seeds; ``None`` unless every seed has a value (a threshold some seed never reached)."""
    values = [s[key] for s in seeds.values()]
    return None if not values or any(v is None for v in values) else float(np.mean(values))


def ratios(methods: dict, ours: str, keys: list[str], budget: int | None = None) -> dict:
    """Frames of the best baseline over ours' per threshold (> 1: ours needs fewer), and our
    completion time over that of the baseline with the highest success rate (< 1: faster).
    With ``budget``, also ``efficiency_at_least``: a seed that never reached a threshold
    counts as ``budget`` frames for a baseline, so the ratio is a lower bound (null unless
    every seed of ours reached it)."""
    baselines = {m: r for m, r in methods.items() if m != ours}
    out = {"efficiency": {}, "efficiency_at_least": {}, "best_baseline": {}}
    for key in keys:
        mine = method_mean(methods[ours]["seeds"], key) if ours in methods else None
        theirs = {m: v for m, r in baselines.items() if (v := method_mean(r["seeds"], key)) is not None}
        best = min(theirs, key=theirs.get) if theirs else None
        out["best_baseline"][key] = best
        out["efficiency"][key] = theirs[best] / mine if best is not None and mine else None
        censored = [np.mean([budget if s[key] is None else s[key] for s in r["seeds"].values()])
                    for r in baselines.values() if r["seeds"]] if budget is not None else []
        out["efficiency_at_least"][key] = float(min(censored)) / mine if censored and mine else None
    by_success = max(baselines, key=lambda m: baselines[m]["success_rate"], default=None)
    t_ours = methods.get(ours, {}).get("completion_time_mean_s")
    t_best = baselines[by_success]["completion_time_mean_s"] if by_success is not None else None
    out["execution_time"] = t_ours / t_best if t_ours is not None and t_best else None
    out["best_baseline"]["execution_time"] = by_success
    return out


def binned(rows: list[dict], key: str, edges: np.ndarray) -> np.ndarray:
    """Episode-weighted means of ``key`` per frame bin (NaN where no episode ended)."""
    sums, counts = np.zeros(len(edges) - 1), np.zeros(len(edges) - 1)
    for r in rows:
        v, n = r.get(key, math.nan), r.get("episodes", 0.0)
        if n > 0 and math.isfinite(v):
            i = min(max(int(np.searchsorted(edges, r["frames"], side="left")) - 1, 0), len(sums) - 1)
            sums[i], counts[i] = sums[i] + v * n, counts[i] + n
    with np.errstate(invalid="ignore"):
        return np.where(counts > 0, sums / np.maximum(counts, 1e-12), np.nan)


def plot_curves(curves: dict[str, dict[int, list[dict]]], budget: int, bins: int, phases: list[tuple[int, str]],
                out: Path) -> list[Path]:
    edges = np.linspace(0, budget, bins + 1)
    x, written = (edges[:-1] + edges[1:]) / 2 / 1e6, []
    for key, ylabel in CURVES.items():
        fig, ax = plt.subplots(figsize=(6.5, 3.8))
        for method, by_seed in curves.items():
            runs = [full_task(rows) if key == "success_rate" else rows for rows in by_seed.values()]
            ys = np.stack([binned(rows, key, edges) for rows in runs if rows] or [np.full(bins, np.nan)])
            with warnings.catch_warnings():  # bins where no seed ended an episode stay NaN
                warnings.simplefilter("ignore", RuntimeWarning)
                mean, lo, hi = np.nanmean(ys, 0), np.nanmin(ys, 0), np.nanmax(ys, 0)
            (line,) = ax.plot(x, mean, label=f"{method} ({len(by_seed)} seeds)")
            ax.fill_between(x, lo, hi, color=line.get_color(), alpha=0.2)
        for start, name in [p for p in phases if p[0] > 0]:  # a phase from frame 0 needs no mark
            ax.axvline(start / 1e6, color="k", lw=0.8, alpha=0.4)
            ax.text(start / 1e6, 1.0, f" {name}", transform=ax.get_xaxis_transform(), fontsize=7, va="top", rotation=90)
        top = LAST_SUBTASK + 0.2 if key == "end_stage" else 1.0
        ax.set(xlabel="training frames (millions)", ylabel=ylabel, ylim=(0, top))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        path = out.with_name(f"{out.stem}_{key}.png")
        fig.savefig(path, dpi=120)
        plt.close(fig)
        written.append(path)
    return written


def method_parameters(tcfg: DictConfig) -> dict[str, int]:
    """Trainable parameters of the method's actor and critic (a 1-world kinematic env for the shapes)."""
    cfg = OmegaConf.merge(tcfg, {"env": {"num_worlds": 1, "backend": "kinematic"}})
    env, models, _ = make_training(cfg)
    env.close()
    return parameter_count(models.actor_net, models.critic_net)


def train_command(cfg: DictConfig, method: str, kinematic: list[str], candidate: str = AS_BUILT) -> str:
    extra = "".join(f" {o}" for o in cfg.train)
    run = f"{cfg.runs_dir}/{run_name(method, candidate, '<seed>')}"
    tuned = "" if candidate == AS_BUILT else f" (+ tuning.candidates.{candidate}'s phase overrides)"
    return (f"python recipes/train.py experiment=table1_{method}{extra} seed=<seed> out_dir={run}"
            f" (seeds not in {list(cfg.mujoco_seeds)}: + pipeline=[{','.join(kinematic)}]){tuned}")


def summary_over_seeds(evals: list[dict], trials: int, backend: str) -> dict:
    t_mean, t_std = pooled_times(evals)
    rates = [e["success_rate"] for e in evals]
    return {"trials": trials, "backend": backend, "seeds_evaluated": len(evals),
            "success_rate": float(np.mean(rates)) if rates else None,
            "success_rate_std_over_seeds": float(np.std(rates)) if rates else None,
            "completion_time_mean_s": t_mean, "completion_time_std_s": t_std}


def train(tcfg: DictConfig) -> None:
    if not run_pipeline(tcfg)["finished"]:
        raise SystemExit(f"stopped during {tcfg.out_dir} (a signal or the wall-time limit); rerun to resume")


def run_seed(cfg: DictConfig, method: str, seed: int, candidate: str = AS_BUILT
             ) -> tuple[dict, list[dict], DictConfig, list]:
    """Train (or resume, or skip) one run and evaluate it: its record, its kinematic rows, its
    full config and where its kinematic phases start. A finished run's rows and evaluations
    are kept in ``cfg.records_dir`` and reused while the run's and evaluations' settings hold."""
    tcfg, full = train_config(cfg, method, seed, candidate)
    path = Path(cfg.records_dir) / f"{run_name(method, candidate, seed)}.json"
    evals = {"eval_kinematic": OmegaConf.to_container(cfg.eval_kinematic, resolve=True)}
    if seed in cfg.mujoco_seeds:
        evals["eval"] = OmegaConf.to_container(cfg.eval, resolve=True)
    kept = reuse_or_finish(path, tcfg, evals, lambda: finish_run(cfg, tcfg, full, evals))
    rows = kept["rows"]
    record = {**efficiency(rows, cfg.thresholds, int(cfg.window)), **kept["record"]}
    return record, rows, full, [tuple(p) for p in kept["phase_starts"]]


def finish_run(cfg: DictConfig, tcfg: DictConfig, full: DictConfig, evals: dict) -> dict:
    """Train (or resume) the run of ``tcfg`` and evaluate it: the payload of its record."""
    run = Path(tcfg.out_dir)
    train(tcfg)
    kin = kinematic_phases(full)
    rows = compact([r for r in run_rows(run) if r["phase"] in kin])
    record = {"wall_s": rows[-1]["wall_s"], "frames": rows[-1]["frames"], "run": str(run),
              "eval_kinematic": evaluate(phase_checkpoint(run, kin[-1]), cfg.eval_kinematic)}
    phases = load_state(run)
    if "eval" in evals:
        record["eval"] = evaluate(phase_checkpoint(run, phases[-1]["name"]), cfg.eval)
        record["wall_s_all_phases"] = sum(p["wall_s"] for p in phases)
    if any("subtask" in r for r in rows):  # Bendikas et al.: how each sub-task ended
        record["subtasks"] = subtask_history(rows)
    starts, start = [], 0
    for p in phases[: len(kin)]:
        starts.append((start, p["name"]))
        start += p["frames"]
    return {"record": record, "rows": rows, "phase_starts": starts, "eval_settings": evals,
            "finished": provenance()}


def run_table1(cfg: DictConfig) -> dict:
    out = Path(cfg.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    t0, prov = time.monotonic(), provenance()  # before any output: the tree is still clean
    if cfg.ours not in cfg.methods:
        raise ValueError(f"ours={cfg.ours!r} is not among methods {list(cfg.methods)}")
    if not set(cfg.mujoco_seeds) <= set(cfg.seeds):
        raise ValueError(f"mujoco_seeds={list(cfg.mujoco_seeds)} must be among seeds={list(cfg.seeds)}")
    check_tuning(cfg)
    tuning = {method: tune(cfg, method, run_seed) for method in cfg.methods}  # the same candidates for each
    done = {}  # seed by seed, every method: each finished seed is a complete row of the comparison
    for seed in cfg.seeds:
        for method in cfg.methods:
            done[method, int(seed)] = run_seed(cfg, method, int(seed), tuning[method]["chosen"])
    methods, curves, budgets = {}, {}, {}
    for method in cfg.methods:
        seeds, curves[method] = {}, {}
        for seed in cfg.seeds:
            seeds[str(seed)], curves[method][int(seed)], full, _ = done[method, int(seed)]
        kin = kinematic_phases(full)  # the method's pipeline is the same for every seed
        budgets[method] = (budget_frames(full), total_frames(full, kin))
        if len(set(budgets.values())) > 1:
            raise ValueError(f"the methods must share one frame budget (all phases, kinematic ones); got {budgets}")
        table = summary_over_seeds([s["eval"] for s in seeds.values() if "eval" in s], int(cfg.eval.trials),
                                   str(cfg.eval.backend))
        methods[method] = {
            "seeds": seeds, **table, "mujoco_seeds": list(cfg.mujoco_seeds),
            "kinematic": summary_over_seeds([s["eval_kinematic"] for s in seeds.values()],
                                            int(cfg.eval_kinematic.trials), str(cfg.eval_kinematic.backend)),
            "budget_frames": budgets[method][0], "kinematic_budget_frames": budgets[method][1],
            "command": train_command(cfg, method, kinematic_phases(full), tuning[method]["chosen"]),
            "parameters": method_parameters(full), "tuning": tuning[method],
        }
    keys = [f"frames_to_{label(m, float(v))}" for m, v in cfg.thresholds.items()]
    kin_budget = next(iter(budgets.values()))[1]  # the same for every method (checked above)
    r = ratios(methods, cfg.ours, keys, kin_budget)
    r_kin = ratios({m: {**v["kinematic"], "seeds": v["seeds"]} for m, v in methods.items()}, cfg.ours, keys)
    # a phase start is marked where every run started it at the same frame (exit rules move them)
    starts = [set(map(tuple, run[3])) for run in done.values()]
    phases = sorted(set.intersection(*starts)) if starts else []
    pngs = plot_curves(curves, kin_budget, int(cfg.curve_bins), phases, out)
    doc = {"methods": methods, "efficiency_ratio": r["efficiency"].get(keys[0]), "efficiency_ratios": r["efficiency"],
           **table1_intervals(methods, cfg.ours, keys[0], r["best_baseline"][keys[0]],
                              r["best_baseline"]["execution_time"]),
           "efficiency_ratios_at_least": r["efficiency_at_least"],
           "execution_time_ratio": r["execution_time"], "execution_time_ratio_kinematic": r_kin["execution_time"],
           "best_baselines": {**r["best_baseline"], "execution_time_kinematic": r_kin["best_baseline"]["execution_time"]},
           "ours": cfg.ours, "thresholds": OmegaConf.to_container(cfg.thresholds), "window_iterations": int(cfg.window),
           "eval": OmegaConf.to_container(cfg.eval), "eval_kinematic": OmegaConf.to_container(cfg.eval_kinematic),
           "plots": [str(p) for p in pngs], "wall_s": time.monotonic() - t0, **prov}
    out.write_text(json.dumps(doc, indent=2) + "\n")
    out.with_suffix(".md").write_text(markdown(doc))
    return doc
