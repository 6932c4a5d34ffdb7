"""The paper's curriculum ablation: 4-stage EE tracking, dynamic vs Liu et al. (max) and (min).

    python recipes/ablation_ee.py                          # 4 methods x 3 seeds, 1000 iterations each
    python recipes/ablation_ee.py seeds=[0] iterations=50  # a quicker look

The work is :mod:`pnp.studies.ablation_ee` (its docstring says what and how).
"""
from __future__ import annotations

import json

import hydra
from omegaconf import DictConfig

from pnp.studies.ablation_ee import run_ablation
from pnp.training.config import register

register()


@hydra.main(config_path="config", config_name="ablation_ee", version_base="1.3")
def main(cfg: DictConfig) -> None:
    doc = run_ablation(cfg)
    for method, s in doc["summary"].items():
        print(method, json.dumps(s))
    print(f"wrote {cfg.out}")


if __name__ == "__main__":
    main()
