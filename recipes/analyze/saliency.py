"""Saliency of a trained teacher (paper Fig. 7): per step, the gradient of the L2 norm of its
mean action with respect to the *normalised* observation (so blocks are comparable),
as shares per block and field, by each robot's stage, over many deterministic episodes.

    python recipes/analyze/saliency.py checkpoint=results/train_dual/dual_mj2/checkpoint.pt out=results/saliency_dual
    python recipes/analyze/saliency.py checkpoint=results/train_single/checkpoint_mujoco.pt out=results/saliency_single

The work is :mod:`pnp.analysis.saliency` (its docstring says what and how).
"""
import sys

from pnp.analysis.saliency import main


if __name__ == "__main__":
    main(sys.argv[1:])
