"""The paper's per-stage baselines in our trainer: Bendikas et al.'s sub-tasks trained one at
a time (``bendikas``) and the choice of schedule, models and loss per method (``per_stage``);
Liu et al.'s schedules are transforms (``pnp.transforms``)."""
