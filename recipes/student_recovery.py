"""The paper's recovery claim, measured: a distilled student and its teacher when the box is
moved away after the lift, and under long mocap dropouts (deterministic policies).

    python recipes/student_recovery.py checkpoint=runs/distill_single out=results/student_recovery.json
    python recipes/student_recovery.py checkpoint=runs/distill_dual trials=50 env.num_worlds=50

The work is :mod:`pnp.studies.student_recovery` (its docstring says what and how).
"""
from __future__ import annotations

from pathlib import Path

import hydra
from omegaconf import DictConfig

from pnp.studies.student_recovery import evaluate
from pnp.training.config import register

register()


@hydra.main(config_path="config", config_name="student_recovery", version_base="1.3")
def main(cfg: DictConfig) -> None:
    result = evaluate(cfg)
    print(Path(result["markdown"]).read_text())
    print(f"wrote {result['json']}")


if __name__ == "__main__":
    main()
