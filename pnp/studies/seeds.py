"""Is a pipeline reliable, or was one run lucky? Several seeds of the same command, each
trained from an empty folder and evaluated on the reporting trials (``make train SEED=k
RUN=runs/seed_k``), gathered into one result with the mean, the worst seed and the spread,
and each goal said to be met or not, by how much.

Every seed's evaluation is on the same paired trials, so trial ``i`` is the same layout for
all of them; ``trials_all_solved`` / ``trials_none_solved`` count the layouts every seed
solved and none did.
"""
from __future__ import annotations

import json
import statistics
from pathlib import Path

from pnp.training.protocol import REPORTING_SEED
from pnp.training.provenance import provenance

# What each seed contributes, copied from its evaluation.
_PER_SEED = ("success_rate", "completion_time_mean_s", "failure_causes", "train_wall_s", "mujoco_frames",
             "env_frames", "from_empty_folder", "launch_commits", "checkpoint", "checkpoint_iteration", "trials")


def _load(run: Path, eval_name: str) -> dict:
    """``run``: a seed's run folder (its ``eval_name`` is read), or that evaluation's JSON itself
    (a run folder is not kept once its evaluation is in results/)."""
    path = run if run.suffix == ".json" else run / eval_name
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no evaluation of this seed's run (make train's last step writes it)")
    result = json.loads(path.read_text())
    if result.get("seed") != REPORTING_SEED:
        raise ValueError(f"{path} was evaluated on seed {result.get('seed')}, not the reporting seed {REPORTING_SEED}")
    if "phases" not in result:
        raise ValueError(f"{path} is not the evaluation of a pipeline folder (no phases): the seeds' costs are unknown")
    return {**result, "eval_file": str(path)}


def _machines(result: dict) -> list[str] | None:
    """The CPUs a seed trained on (its launches'; None: not recorded). Wall time is per machine
    kind: the same phases ran ~1.5x slower on an Intel Xeon than on an AMD EPYC here."""
    launches = result.get("pipeline_launches")
    return sorted({entry["machine"] for entry in launches}) if launches else None


def goal_checks(seeds: dict, summary: dict, commits: list[str], goals: dict) -> dict:
    """Each goal with the measured value and whether it is met (``None``: not measured)."""
    def check(value, limit, at_least: bool) -> dict:
        met = None if value is None else (value >= limit if at_least else value <= limit)
        return {"goal": limit, "measured": value, "met": met}

    worst_wall = max((s["train_wall_s"] for s in seeds.values()), default=None)
    frames = [s["mujoco_frames"] for s in seeds.values()]
    return {
        "mean_success": check(summary["success_rate_mean"], goals["mean_success"], True),
        "worst_success": check(summary["success_rate_worst"], goals["worst_success"], True),
        "max_train_wall_s": check(worst_wall, goals["max_train_wall_s"], False),
        "max_mujoco_frames": check(None if None in frames else max(frames), goals["max_mujoco_frames"], False),
        "from_empty_folders": {"met": all(s["from_empty_folder"] is True for s in seeds.values())},
        "one_commit": {"met": len(commits) == 1},
    }


def seed_study(runs: list[Path], eval_name: str, goals: dict, command: str) -> dict:
    """``runs``: the seeds' run folders or evaluation files. Returns the multi-seed result, keyed by training seed."""
    evals = {}
    for run in runs:
        result = _load(Path(run), eval_name)
        seed = result["train_seed"]
        if seed in evals:
            raise ValueError(f"{result['eval_file']} and {evals[seed]['eval_file']} were both trained with seed {seed}")
        evals[seed] = result
    evals = dict(sorted(evals.items()))
    trials = {r["trials"] for r in evals.values()}
    if len(trials) != 1:
        raise ValueError(f"the seeds were evaluated on different trial counts {sorted(trials)}: not paired")
    seeds = {str(seed): {k: r.get(k) for k in _PER_SEED} | {"eval_file": r["eval_file"], "launch_machines": _machines(r)}
             for seed, r in evals.items()}
    rates = [s["success_rate"] for s in seeds.values()]
    solved = [[rec[1] for rec in r["trial_records"]] for r in evals.values()]
    commits = sorted({c for s in seeds.values() for c in s["launch_commits"]})
    summary = {
        "success_rate_mean": statistics.fmean(rates), "success_rate_worst": min(rates), "success_rate_best": max(rates),
        "success_rate_spread": max(rates) - min(rates),
        "success_rate_std": statistics.stdev(rates) if len(rates) > 1 else None,
        "trials_all_solved": sum(all(t) for t in zip(*solved)), "trials_none_solved": sum(not any(t) for t in zip(*solved)),
    }
    return {
        "seeds": seeds, "num_seeds": len(seeds), **summary, "trials_per_seed": trials.pop(),
        "reporting_seed": REPORTING_SEED, "paired": True,
        "commit": commits[0] if len(commits) == 1 else None, "launch_commits": commits,
        "goals": goal_checks(seeds, summary, commits, goals),
        # "commit" is the seeds' training commit; this gathering's own provenance is apart.
        "gathered": provenance(command=command),
    }


def _millions(frames: int | None) -> str:
    return "?" if frames is None else f"{frames / 1e6:.1f}"


def seeds_markdown(result: dict, title: str) -> str:
    rows = "".join(f"| {seed} | {100 * s['success_rate']:.1f} | {s['train_wall_s'] / 3600:.2f} | "
                   f"{_millions(s['mujoco_frames'])} | {s['from_empty_folder']} | "
                   f"{' + '.join(s['launch_machines'] or ['not recorded'])} |\n"
                   for seed, s in result["seeds"].items())
    goals = "".join(f"- {name}: {'met' if g['met'] else ('not measured' if g['met'] is None else 'NOT met')}"
                    + (f" ({g['measured']} against {g['goal']})" if "goal" in g else "") + "\n"
                    for name, g in result["goals"].items())
    return (f"# {title}\n\n| Seed | Success (%) | Training (h) | MuJoCo frames (M) | From an empty folder | "
            f"Trained on |\n| --- | --- | --- | --- | --- | --- |\n{rows}\n"
            f"Mean {100 * result['success_rate_mean']:.1f} %, worst {100 * result['success_rate_worst']:.1f} %, "
            f"spread {100 * result['success_rate_spread']:.1f} points over {result['num_seeds']} seeds, "
            f"{result['trials_per_seed']} paired trials each on seed {result['reporting_seed']}; "
            f"{result['trials_all_solved']} layouts solved by every seed, {result['trials_none_solved']} by none.\n\n"
            f"Goals:\n{goals}")


def plot_seeds(result: dict, path: Path) -> None:
    """Each seed's success rate and training hours, beside the goals."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    seeds = list(result["seeds"])
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(8, 3))
    ax1.bar(seeds, [100 * result["seeds"][k]["success_rate"] for k in seeds], color="tab:blue")
    for name, style in (("mean_success", "--"), ("worst_success", ":")):
        ax1.axhline(100 * result["goals"][name]["goal"], color="k", ls=style, lw=1, label=f"goal: {name}")
    ax1.set(xlabel="training seed", ylabel="success on the reporting trials (%)", ylim=(0, 100))
    ax1.legend(loc="lower right", fontsize=7)
    ax2.bar(seeds, [result["seeds"][k]["train_wall_s"] / 3600 for k in seeds], color="tab:orange")
    ax2.axhline(result["goals"]["max_train_wall_s"]["goal"] / 3600, color="k", ls="--", lw=1, label="goal")
    ax2.set(xlabel="training seed", ylabel="training wall time (h)")
    ax2.legend(loc="lower right", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
