"""The training core the recipes compose: the configuration schema (``config``), models,
tasks (env factory), collection, the PPO update, the trainer and pipelines, checkpoints,
the rollout/evaluation API, checkpoint selection, the evaluation protocol and provenance.
Distillation (``pnp.distill``), the baselines (``pnp.baselines``) and the studies
(``pnp.studies``) build on it. Needs the ``[sim,train]`` extras."""
