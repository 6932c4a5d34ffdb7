"""Distil a deployable student from a trained teacher (paper Sec. III-C).

    python recipes/distill.py distill_experiment=single out_dir=runs/distill_single   # rerun to resume
    python recipes/distill.py distill_experiment=dual out_dir=runs/distill_dual
    python recipes/distill.py distill.teacher=runs/<teacher run> distill.beta=0.5 noise.scale=2
    python recipes/distill.py distill.beta_final=0.1 distill.anneal_iterations=500 logger.backend=csv

The student sees noisy observations (per-field Gaussian noise, mocap dropouts of the box
pose), no stage, and a history of its arm joints instead of its EE pose; it acts on its
own and learns by PPO on the stage-wise reward at fixed mu_j plus beta * KL to the frozen
teacher, which reads the clean observation and stage of the same states. The run folder
(``runs/distill_<date>`` unless ``out_dir=``) receives ``checkpoint.pt`` (every
``checkpoint_every_min`` minutes and at the end), ``metrics.jsonl`` (one line per
iteration, with ``train/kl_teacher`` and ``beta``), the training plots and the logger's
files. A folder that holds a checkpoint resumes from it. Keys, defaults and the noise
model: ``pnp/distill/config.py``; the pieces: ``pnp.distill.trainer``.
Evaluate with ``recipes/evaluate_student.py``.
"""
from __future__ import annotations

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from pnp.distill.config import register
from pnp.distill.trainer import distill

register()


@hydra.main(config_path="config", config_name="distill", version_base="1.3")
def main(cfg: DictConfig) -> None:
    if cfg.out_dir is None:
        cfg.out_dir = HydraConfig.get().runtime.output_dir
    distill(cfg)


if __name__ == "__main__":
    main()
