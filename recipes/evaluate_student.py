"""Evaluate a distilled student beside its teacher over N trials each (deterministic policies).

    python recipes/evaluate_student.py checkpoint=runs/distill_single out=results/eval_student_single.json
    python recipes/evaluate_student.py checkpoint=runs/distill_dual trials=100 env.num_worlds=100

The work is :mod:`pnp.distill.evaluation` (its docstring says what and how).
"""
from __future__ import annotations

from pathlib import Path

import hydra
from omegaconf import DictConfig

from pnp.distill.evaluation import evaluate
from pnp.training.config import register

register()


@hydra.main(config_path="config", config_name="evaluate_student", version_base="1.3")
def main(cfg: DictConfig) -> None:
    result = evaluate(cfg)
    print(Path(result["markdown"]).read_text())
    print(f"wrote {result['json']}")


if __name__ == "__main__":
    main()
