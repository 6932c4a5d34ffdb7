"""What the recipes compose: the configuration schema (``config``), models, tasks (env
factory), collection, the PPO update, the trainer and pipelines, checkpoints, the
rollout/evaluation API, and teacher-student distillation (``student``, ``distill``).
Needs the ``[sim,train]`` extras."""
