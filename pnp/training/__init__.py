"""What the recipes compose: the configuration schema (``config``), models, tasks (env
factory), collection, the PPO update, the trainer and pipelines, checkpoints, the
rollout/evaluation API, teacher-student distillation (``student``, ``distill``) and its
recovery measurement (``recovery``).
Needs the ``[sim,train]`` extras."""
