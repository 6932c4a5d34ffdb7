"""Speed of the kinematic backend through the TorchRL env, with a time breakdown.

    python recipes/bench_kinematic.py                     # prints the table
    python recipes/bench_kinematic.py --threads 1 --out results/benchmark_kinematic.json

The work is :mod:`pnp.analysis.bench_kinematic` (its docstring says what and how).
"""
from pnp.analysis.bench_kinematic import main


if __name__ == "__main__":
    main()
