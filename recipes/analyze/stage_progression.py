"""Share of episodes in each stage over training (the paper's Fig. 5), with curriculum
regressions detected and shaded.

    python recipes/analyze/stage_progression.py results/stage_progression_dual \

The work is :mod:`pnp.analysis.stage_progression` (its docstring says what and how).
"""
import sys

from pnp.analysis.stage_progression import main


if __name__ == "__main__":
    main(sys.argv[1:])
