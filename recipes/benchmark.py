"""Env speed against raw MuJoCo on the same work, side by side in one process.

    python recipes/benchmark.py                      # writes results/benchmark_env.json
    python recipes/benchmark.py --batches 64 --steps 5 --out /tmp/b.json
    python recipes/benchmark.py --robots 1 --batches 64 256 --low-level-checkpoint runs/loco

The work is :mod:`pnp.analysis.benchmark_env` (its docstring says what and how).
"""
from pnp.analysis.benchmark_env import main


if __name__ == "__main__":
    main()
