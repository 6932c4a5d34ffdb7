"""Which robot parts touch the unheld box, and which touched it just before it tipped (MuJoCo).

    python recipes/analyze/box_contacts.py checkpoint=results/run18_single_pnp_checkpoint.pt         out=runs/box_contacts.json trials=100 seed=777 env.num_worlds=100

The work is :mod:`pnp.analysis.box_contacts` (its docstring says what and how).
"""
import sys

from pnp.analysis.box_contacts import main


if __name__ == "__main__":
    main(sys.argv[1:])
