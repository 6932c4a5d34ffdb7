"""Training plots from a run's ``metrics.jsonl``; the trainer calls this at the end of a run.

    python -m pnp.training.plots runs/<run>/metrics.jsonl [out_dir]

Writes ``mean_end_stage.png`` (mean end-of-episode stage vs iteration), ``stage_shares.png``
(share of episodes ending in each stage, stacked) and ``rho.png`` (mean rho_j per term;
only for the dynamic schedule).
"""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def load_metrics(path: str | Path) -> list[dict]:
    return [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]


def _series(rows: list[dict], key: str) -> np.ndarray:
    return np.array([r.get(key, math.nan) for r in rows], dtype=float)


def plot_training(metrics_path: str | Path, out_dir: str | Path | None = None,
                  phases: list[tuple[float, str]] = ()) -> list[Path]:
    """Write the PNGs next to the metrics (or into ``out_dir``); returns their paths.
    ``phases``: (first iteration, name) of each pipeline phase, marked on every plot."""
    rows = load_metrics(metrics_path) if Path(metrics_path).is_file() else []
    out_dir = Path(out_dir) if out_dir is not None else Path(metrics_path).parent
    out_dir.mkdir(parents=True, exist_ok=True)
    if not rows:
        return []
    it = _series(rows, "iteration")
    written = []

    shares = sorted({k for r in rows for k in r if k.startswith("stage_share/")}, key=lambda k: int(k.split("S")[-1]))
    fig, ax = plt.subplots(figsize=(6, 3.5))
    stage = _series(rows, "mean_end_stage")
    ok = np.isfinite(stage)  # iterations where no episode ended have no value
    final = _series(rows, "mean_final_stage")
    peak = np.isfinite(final).any()  # lambda(e) is the peak stage: show the final stage beside it
    ax.plot(it[ok], stage[ok], label="highest stage reached (lambda)" if peak else None)
    if peak:
        ax.plot(it[ok], final[ok], "--", label="final stage")
        ax.legend(fontsize=8)
    ax.set(xlabel="iteration", ylabel="mean end-of-episode stage", ylim=(0, max(len(shares), 2) - 0.8))
    ax.grid(alpha=0.3)
    written.append(_save(fig, out_dir / "mean_end_stage.png", phases))

    if shares:
        fig, ax = plt.subplots(figsize=(6, 3.5))
        ys = np.stack([_series(rows, k) for k in shares])
        ok = np.isfinite(ys).all(0)
        ax.stackplot(it[ok], ys[:, ok], labels=[k.split("/")[-1] for k in shares])
        ylabel = "share of episodes by highest stage" if peak else "share of episodes ending in stage"
        ax.set(xlabel="iteration", ylabel=ylabel, ylim=(0, 1))
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1), fontsize=8)
        written.append(_save(fig, out_dir / "stage_shares.png", phases))

    succ, eps = _series(rows, "success_rate"), _series(rows, "episodes")
    ok = np.isfinite(succ) & (np.nan_to_num(eps) > 0)
    if ok.any():  # episodes end in bursts: dots per iteration, line over windows weighted by episodes
        fig, ax = plt.subplots(figsize=(6, 3.5))
        ax.plot(it[ok], succ[ok], ".", ms=3, alpha=0.3, label="per iteration")
        w = max(1, len(rows) // 50)
        x, y = [], []
        for i in range(0, len(rows), w):
            m = ok[i:i + w]
            if m.any():
                x.append(it[i:i + w][m].mean())
                y.append(np.average(succ[i:i + w][m], weights=eps[i:i + w][m]))
        ax.plot(x, y, "-", label=f"over {w}-iteration windows")
        ax.set(xlabel="iteration", ylabel="training success rate (stochastic policy)", ylim=(0, 1))
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
        written.append(_save(fig, out_dir / "success_rate.png", phases))

    rho = sorted({k for r in rows for k in r if k.startswith("rho/")})
    if rho:
        fig, ax = plt.subplots(figsize=(7, 4))
        for k in rho:
            ax.plot(it, _series(rows, k), label=k.split("/", 1)[1])
        ax.set(xlabel="iteration", ylabel="mean rho_j (over worlds and robots)", yscale="log")
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1), fontsize=7)
        ax.grid(alpha=0.3, which="both")
        written.append(_save(fig, out_dir / "rho.png", phases))
    return written


def plot_pipeline(out_dir: str | Path, phases: list[dict]) -> list[Path]:
    """The training plots over a whole pipeline: every phase's metrics on one iteration
    axis (``pipeline_metrics.jsonl``), phase starts marked."""
    out_dir, rows, marks, offset = Path(out_dir), [], [], 0
    for i, phase in enumerate(phases):
        marks.append((offset + 0.5, phase["name"]))
        for r in load_metrics(Path(phase["checkpoint"]).parent / "metrics.jsonl"):
            rows.append({**r, "iteration": offset + r["iteration"], "phase": i})
        offset += phase["iterations"]
    path = out_dir / "pipeline_metrics.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    return plot_training(path, out_dir, marks)


def _save(fig, path: Path, phases: list[tuple[float, str]] = ()) -> Path:
    for ax in fig.axes:
        for x, name in phases:
            ax.axvline(x, color="k", lw=0.8, alpha=0.5)
            ax.text(x, 1.0, f" {name}", transform=ax.get_xaxis_transform(), fontsize=7, va="top", rotation=90)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


if __name__ == "__main__":
    if len(sys.argv) not in (2, 3):
        sys.exit(__doc__)
    for p in plot_training(sys.argv[1], sys.argv[2] if len(sys.argv) == 3 else None):
        print(p)


def plot_selection(result: dict, out: Path) -> None:
    """Success per candidate checkpoint and selection seed, the chosen one marked (recipes/select_checkpoint.py)."""
    fig, ax = plt.subplots(figsize=(6, 3.5))
    its = [c["iteration"] for c in result["candidates"]]
    for seed in result["seeds"]:
        ax.plot(its, [100 * c["success"][str(seed)] for c in result["candidates"]], "o-", label=f"seed {seed}")
    ax.axvline(result["selected_iteration"], color="k", ls=":", label="selected")
    ax.set(xlabel="iteration of the last phase", ylabel="success (%)",
           title=f"selection: {result['trials']} deterministic trials per seed")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)
