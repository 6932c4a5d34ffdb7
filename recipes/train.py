"""Train the high-level teacher with MAPPO and the dynamic reward curriculum (paper Sec. III).

    python recipes/train.py                                   # one robot, MuJoCo, the schema's defaults (pnp/training/config.py)
    python recipes/train.py experiment=dual_pnp_mujoco        # a quoted result's configuration
    python recipes/train.py experiment=single_pnp_pipeline out_dir=runs/main   # phases; rerun to resume
    python recipes/train.py backend=kinematic env.num_worlds=256 env.max_episode_steps=150
    python recipes/train.py curriculum.schedule=liu_max logger.backend=csv
    python recipes/train.py resume=true                       # newest runs/**/checkpoint.pt
    python recipes/train.py warm_start=runs/<run>/checkpoint.pt

The run folder (``runs/train_<date>`` unless ``out_dir=``) receives ``checkpoint.pt``
(every ``checkpoint_every_min`` minutes and at the end), ``metrics.jsonl`` (one line per
iteration), the training plots (``*.png``) and the logger's files (wandb offline or csv).
A resumed run continues in its checkpoint's folder, bit for bit. Keys and defaults:
``pnp/training/config.py``; the pieces: ``pnp.training.trainer``.
"""
from __future__ import annotations


import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from pnp.training.config import register
from pnp.training.pipeline import run_pipeline
from pnp.training.trainer import resume_in_place, train

register()


@hydra.main(config_path="config", config_name="train", version_base="1.3")
def main(cfg: DictConfig) -> None:
    if cfg.out_dir is None:
        cfg.out_dir = HydraConfig.get().runtime.output_dir
    if cfg.pipeline:  # an experiment of phases (e.g. experiment=single_pnp_pipeline): resumes by itself
        if not run_pipeline(cfg)["finished"]:
            raise SystemExit(f"stopped before the pipeline's end; the same command resumes in {cfg.out_dir}")
    else:
        train(resume_in_place(cfg))


if __name__ == "__main__":
    main()
