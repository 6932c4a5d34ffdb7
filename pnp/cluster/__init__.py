"""Many runs on a Ray cluster (``pnp.cluster.ray_runs``)."""
