"""A diagnostic checkpoint: one run's actor with another run's critic, to ask which of the two
a difference in learning lives in (docs/pipeline_single/run_17.md).

    python recipes/analyze/swap_critic.py actor_from=runs/main17/4_mujoco/checkpoint.pt         critic_from=runs/chain/mj_ft5_1861.pt out=runs/chain/main17_mujoco_chaincritic.pt

The work is :mod:`pnp.analysis.swap_critic` (its docstring says what and how).
"""
import sys

from pnp.analysis.swap_critic import main


if __name__ == "__main__":
    main(sys.argv[1:])
