"""Iteration time and frames/s against threads and device (what a bigger machine buys).

    python recipes/analyze/scaling.py threads=1,2 out=results/scaling.json

The work is :mod:`pnp.analysis.scaling` (its docstring says what and how).
"""
import sys

from pnp.analysis.scaling import main


if __name__ == "__main__":
    main(sys.argv[1:])
