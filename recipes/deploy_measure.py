"""The deployment's measurements into results/ (pnp.deploy.measure; every process on loopback,
real time). Each needs a quiet machine: the world and the clients keep a 10 Hz clock.

    python recipes/deploy_measure.py team --checkpoint results/eval_student_single_checkpoint.pt --out results/deploy_single.json
    python recipes/deploy_measure.py team --checkpoint results/eval_student_dual_checkpoint.pt --out results/deploy_dual.json
    python recipes/deploy_measure.py dropouts --checkpoint results/eval_student_dual_checkpoint.pt --out results/deploy_dropouts.json
    python recipes/deploy_measure.py latency --out results/deploy_latency.json   # read from the two team files
    python recipes/deploy_measure.py plot --out results/deploy_success_vs_delay.png

``team``: the fault-free paired comparison and the delay x loss grid (~1.5 h for 200 trials).
Trailing key=value pairs override pnp.deploy.config.DeployConfig (worlds=, time_scale=, ...).
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from pnp.deploy import measure
from pnp.training.provenance import check_clean, provenance, write_result

TEAM_FILES = {"one robot": "results/deploy_single.json", "two robots": "results/deploy_dual.json"}


def _team_md(r: dict) -> str:
    ff = r["fault_free"]
    rows = "".join(f"| {x['delay_s']:.2f} | {100 * x['loss']:.0f} | {100 * x['success_rate']:.1f} | "
                   f"{x['completion_time_mean_s'] or float('nan'):.2f} |\n" for x in r["grid"])
    lo, hi = ff["paired"]["success_diff_interval"]
    return (f"Deployed student `{r['checkpoint']}`, {r['trials']} trials per row (seed {r['seed']}).\n\n"
            f"Fault-free: deployed {100 * ff['deployed']['success_rate']:.1f} %, in process "
            f"{100 * ff['in_process']['success_rate']:.1f} % (paired difference interval {100 * lo:.1f} to "
            f"{100 * hi:.1f} points).\n\n| delay (s) | loss (%) | success (%) | time (s) |\n| --- | --- | --- | --- |\n"
            + rows)


def team(args, overrides) -> None:
    base = measure.base_config(args.checkpoint, args.trials, overrides)
    with tempfile.TemporaryDirectory(prefix="deploy_measure_") as tmp:
        t0 = time.monotonic()
        work = Path(tmp)
        result = {"checkpoint": args.checkpoint, "trials": args.trials, "seed": base.seed,
                  "fault_free": measure.fault_free(base, work),
                  "grid": measure.grid(base, work, args.delays or measure.DELAYS_S, args.losses or measure.LOSSES)}
        result["wall_s"] = time.monotonic() - t0
    write_result({**result, **provenance()}, args.out, _team_md(result))


def dropouts(args, overrides) -> None:
    from pnp.distill.config import distill_config
    from pnp.training.checkpoint import load_checkpoint

    base = measure.base_config(args.checkpoint, args.trials, overrides)
    teacher = str(distill_config(load_checkpoint(args.checkpoint)["cfg"]).distill.teacher)
    with tempfile.TemporaryDirectory(prefix="deploy_measure_") as tmp:
        t0 = time.monotonic()
        rows = measure.dropouts(base, Path(tmp), teacher)
    md = "| dropout (s) | student deployed (%) | teacher in process (%) |\n| --- | --- | --- |\n" + "".join(
        f"| {r['dropout_s']} | {100 * r['student_deployed']['success_rate']:.1f} | "
        f"{100 * r['teacher_in_process']['success_rate']:.1f} |\n" for r in rows)
    write_result({"checkpoint": args.checkpoint, "teacher": teacher, "trials": args.trials, "rows": rows,
                  "wall_s": time.monotonic() - t0, **provenance()}, args.out, md)


def latency(args, _) -> None:
    rows = {}
    for task, path in TEAM_FILES.items():
        ff = json.loads(Path(path).read_text())["fault_free"]
        rows[task] = {"control_loop": ff["latency"], "inference": ff["inference"], "source": path}
    md = "".join(f"- {task}: " + ", ".join(f"{robot} p50 {v['p50_ms']:.1f} ms, p99 {v['p99_ms']:.1f} ms"
                                          for robot, v in r["control_loop"].items() if v) + "\n"
                 for task, r in rows.items())
    write_result({"budget_ms": 100.0, "rows": rows, **provenance()}, args.out, md)


def plot(args, _) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    check_clean(args.out, None)
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4), sharey=True)
    for ax, (task, path) in zip(axes, TEAM_FILES.items()):
        team = json.loads(Path(path).read_text())
        grid = team["grid"]
        for loss in sorted({r["loss"] for r in grid}):
            rows = sorted((r for r in grid if r["loss"] == loss), key=lambda r: r["delay_s"])
            ax.plot([1000 * r["delay_s"] for r in rows], [100 * r["success_rate"] for r in rows], "o-",
                    label=f"{100 * loss:.0f} % loss")
        ax.axhline(100 * team["fault_free"]["in_process"]["success_rate"], color="grey", ls="--", lw=1,
                   label="in process, no faults")
        # 50 and 100 ms fall in the same 10 Hz tick, so those two columns coincide.
        ax.set(title=task, xlabel="link delay (ms); the policy ticks every 100 ms",
               xticks=sorted({1000 * r["delay_s"] for r in grid}))
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("success (%)")
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(args.out, dpi=120)
    print(f"wrote {args.out}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("what", choices=["team", "dropouts", "latency", "plot"])
    parser.add_argument("--checkpoint")
    parser.add_argument("--trials", type=int, default=200)
    parser.add_argument("--out", required=True)
    parser.add_argument("--delays", type=float, nargs="*", help="link delays (s) of the grid (default: the issue's)")
    parser.add_argument("--losses", type=float, nargs="*", help="message losses of the grid")
    args, overrides = parser.parse_known_args()
    if args.what in ("team", "dropouts") and not args.checkpoint:
        parser.error(f"{args.what} needs --checkpoint")
    check_clean(args.out, None)
    {"team": team, "dropouts": dropouts, "latency": latency, "plot": plot}[args.what](args, overrides)


if __name__ == "__main__":
    main()
