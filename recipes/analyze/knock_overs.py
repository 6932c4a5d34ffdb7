"""How often a checkpoint's deterministic policy knocks the box over, and whether it recovers.

    python recipes/analyze/knock_overs.py checkpoint=results/run18_single_pnp_checkpoint.pt         out=runs/knock_overs.json trials=200 seed=777 env.num_worlds=200

The work is :mod:`pnp.analysis.knock_overs` (its docstring says what and how).
"""
import sys

from pnp.analysis.knock_overs import main


if __name__ == "__main__":
    main(sys.argv[1:])
