"""Evaluate a trained teacher over N trials with the deterministic policy (paper Table I).

    python recipes/evaluate.py                                   # newest runs/**/checkpoint.pt, 500 trials
    python recipes/evaluate.py checkpoint=runs/<run> trials=100 env.backend=kinematic out=runs/eval.json
    python recipes/evaluate.py checkpoint=runs/main selected=true  # the checkpoint recipes/select_checkpoint.py chose

The work is :mod:`pnp.training.evaluation` (its docstring says what and how).
"""
from __future__ import annotations

from pathlib import Path

import hydra
from omegaconf import DictConfig

from pnp.training.config import register
from pnp.training.evaluation import evaluate

register()


@hydra.main(config_path="config", config_name="evaluate", version_base="1.3")
def main(cfg: DictConfig) -> None:
    result = evaluate(cfg)
    print(Path(result["markdown"]).read_text())
    print(f"wrote {result['json']}")


if __name__ == "__main__":
    main()
