"""Choose a run's checkpoint on seeds other than the reporting one (selection honesty).

    python recipes/select_checkpoint.py run=runs/main              # after the training
    python recipes/evaluate.py checkpoint=runs/main selected=true # then the reporting seed

The work is :mod:`pnp.training.selection` (its docstring says what and how).
"""
from __future__ import annotations

from pathlib import Path

import hydra
from omegaconf import DictConfig

from pnp.training.config import register
from pnp.training.plots import plot_selection
from pnp.training.selection import select

register()


@hydra.main(config_path="config", config_name="select_checkpoint", version_base="1.3")
def main(cfg: DictConfig) -> None:
    run = Path(str(cfg.run))
    result = select(run, int(cfg.candidates), list(cfg.seeds), int(cfg.trials), int(cfg.num_worlds),
                    bool(cfg.progress), nthread=cfg.nthread)
    plot_selection(result, run / "selection.png")
    for c in result["candidates"]:
        print(f"iteration {c['iteration']:6d}: " + ", ".join(f"seed {s} {100 * v:.1f} %" for s, v in c["success"].items()))
    print(f"selected iteration {result['selected_iteration']}: {result['selected']} (wrote {run / 'selection.json'})")


if __name__ == "__main__":
    main()
