"""Where a checkpoint's robots fall: in which stage, carrying or not, and under what commands.

    python recipes/analyze/falls.py checkpoint=results/eval_dual_pnp_learned_ll_checkpoint.pt out=runs/falls.json trials=200 seed=777

The work is :mod:`pnp.analysis.falls` (its docstring says what and how).
"""
import sys

from pnp.analysis.falls import main


if __name__ == "__main__":
    main(sys.argv[1:])
