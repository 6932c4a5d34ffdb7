"""The learned low level's quality (issue 24), measured: velocity tracking over a grid of
commands, EE tracking after 0.1/0.3/1 s against the ideal low level, falls under pushes
while carrying, and how often the leg servos saturate.

    python recipes/ll_quality.py checkpoint=runs/loco out=results/ll_quality.json
    python recipes/ll_quality.py checkpoint=runs/loco pushes.episodes=16 ee.worlds=8   # quick look

The work is :mod:`pnp.studies.ll_quality_report` (its docstring says what and how).
"""
from __future__ import annotations

from pathlib import Path

import hydra
import torch
from omegaconf import DictConfig

from pnp.studies.ll_quality_report import measure
from pnp.training.config import register

register()


@hydra.main(config_path="config", config_name="ll_quality", version_base="1.3")
def main(cfg: DictConfig) -> None:
    torch.set_num_threads(1)
    result = measure(cfg)
    print(Path(result["markdown"]).read_text())
    print(f"wrote {result['json']}")


if __name__ == "__main__":
    main()
