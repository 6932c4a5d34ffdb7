"""How grasps end under a checkpoint's *stochastic* policy: opened by the policy, or lost
with the gripper still closed (drift off the bar, out of reach).

    python recipes/analyze/grasp_losses.py checkpoint=results/train_dual/dual_bb1/checkpoint.pt         out=runs/grasp_losses.json env.handle_order=own_last env.handle_claim=true

The work is :mod:`pnp.analysis.grasp_losses` (its docstring says what and how).
"""
import sys

from pnp.analysis.grasp_losses import main


if __name__ == "__main__":
    main(sys.argv[1:])
