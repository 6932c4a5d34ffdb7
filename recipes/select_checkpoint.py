"""Choose a run's checkpoint on seeds other than the reporting one (selection honesty).

    python recipes/select_checkpoint.py run=runs/main              # after the training
    python recipes/evaluate.py checkpoint=runs/main selected=true # then the reporting seed

The candidates are the newest ``candidates`` snapshots of the run's newest phase (train
with ``snapshot_every``) and its last checkpoint, each judged by ``trials`` deterministic
MuJoCo (or the run's backend) trials per selection seed; the highest mean success wins.
Writes ``<run>/selection.json`` and ``<run>/selection.png`` (success per candidate and seed).
"""
from __future__ import annotations

from pathlib import Path

import hydra
import matplotlib
from omegaconf import DictConfig

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from pnp.training.selection import select  # noqa: E402


def plot(result: dict, out: Path) -> None:
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


@hydra.main(config_path="config", config_name="select_checkpoint", version_base="1.3")
def main(cfg: DictConfig) -> None:
    run = Path(str(cfg.run))
    result = select(run, int(cfg.candidates), list(cfg.seeds), int(cfg.trials), int(cfg.num_worlds),
                    bool(cfg.progress), nthread=int(cfg.nthread))
    plot(result, run / "selection.png")
    for c in result["candidates"]:
        print(f"iteration {c['iteration']:6d}: " + ", ".join(f"seed {s} {100 * v:.1f} %" for s, v in c["success"].items()))
    print(f"selected iteration {result['selected_iteration']}: {result['selected']} (wrote {run / 'selection.json'})")


if __name__ == "__main__":
    main()
