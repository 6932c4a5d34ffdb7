"""The comparison with the paper's baselines: Table I, Fig. 6 and the training-efficiency claim.

    python recipes/table1.py                               # 5 methods x 3 seeds, then 500 MuJoCo trials each
    python recipes/table1.py methods=[dynamic,bendikas] seeds=[0]   # a subset

The work is :mod:`pnp.studies.table1` (its docstring says what and how).
"""
from __future__ import annotations

import hydra
from omegaconf import DictConfig

from pnp.studies.table1 import run_table1
from pnp.training.config import register

register()


@hydra.main(config_path="config", config_name="table1", version_base="1.3")
def main(cfg: DictConfig) -> None:
    doc = run_table1(cfg)
    for method, m in doc["methods"].items():
        kin = m["kinematic"]
        print(method, f"MuJoCo success {m['success_rate']} time {m['completion_time_mean_s']}",
              f"kinematic success {kin['success_rate']:.3f} time {kin['completion_time_mean_s']}",
              {s: {k: v for k, v in r.items() if k.startswith("frames_to")} for s, r in m["seeds"].items()})
    print(f"efficiency ratio {doc['efficiency_ratio']}, execution time ratio {doc['execution_time_ratio']}")
    print(f"wrote {cfg.out}")


if __name__ == "__main__":
    main()
