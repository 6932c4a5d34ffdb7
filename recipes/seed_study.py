"""Several seeds of one pipeline, each trained from an empty folder and evaluated on the
reporting trials, gathered into one result: per seed and the mean, worst and spread.

    make train SEED=0 RUN=runs/seed_0; make train SEED=1 RUN=runs/seed_1; make train SEED=2 RUN=runs/seed_2
    python recipes/seed_study.py runs=[runs/seed_0,runs/seed_1,runs/seed_2] out=results/repro_single_pnp.json

The work is :mod:`pnp.studies.seeds`; goals and defaults: ``recipes/config/seed_study.yaml``.
"""
from __future__ import annotations

from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

from pnp.studies.seeds import plot_seeds, seed_study, seeds_markdown
from pnp.training.config import register
from pnp.training.provenance import check_clean, provenance, write_result

register()


@hydra.main(config_path="config", config_name="seed_study", version_base="1.3")
def main(cfg: DictConfig) -> None:
    check_clean(cfg.out, cfg.dirty_reason)
    result = seed_study([Path(str(r)) for r in cfg.runs], str(cfg.eval_name),
                        OmegaConf.to_container(cfg.goals), provenance()["command"])
    if cfg.dirty_reason is not None:
        result["dirty_reason"] = cfg.dirty_reason
    out = Path(str(cfg.out))
    write_result(result, out, seeds_markdown(result, str(cfg.title)))
    plot_seeds(result, out.with_suffix(".png"))
    print(seeds_markdown(result, str(cfg.title)))


if __name__ == "__main__":
    main()
