"""What the recipes compose: the configuration schema (``config``), models, tasks (env
factory), collection, the PPO update, the trainer and pipelines, checkpoints, and the
rollout/evaluation API. Needs the ``[sim,train]`` extras."""
