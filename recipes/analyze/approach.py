"""Where the gripper is while it approaches the unheld box, and just before the box tips.

    python recipes/analyze/approach.py checkpoint=results/run18_single_pnp_checkpoint.pt         out=runs/approach.json trials=100 seed=777 env.num_worlds=100

The work is :mod:`pnp.analysis.approach` (its docstring says what and how).
"""
import sys

from pnp.analysis.approach import main


if __name__ == "__main__":
    main(sys.argv[1:])
