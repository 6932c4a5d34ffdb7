"""A training run's curve as a table: per window of iterations, training success and the share
of episodes ending in S0 (both weighted by episode counts, as the pipeline's exit rules are),
with the PPO step's KL, learning rate, clip fraction and explained variance averaged.

    python recipes/analyze/training_curve.py metrics=runs/main/5_mujoco_sharp/metrics.jsonl window=100

The work is :mod:`pnp.analysis.training_curve` (its docstring says what and how).
"""
import sys

from pnp.analysis.training_curve import main


if __name__ == "__main__":
    main(sys.argv[1:])
