"""Render one episode offscreen on the CPU (MUJOCO_GL=egl, Debian's Mesa) to GIF or MP4.

    python recipes/render.py                                  # scripted policy, one robot
    python recipes/render.py --out results/scripted_pnp.gif --seed 3 --every 2
    python recipes/render.py --robots 2 --out results/scripted_dual_pnp.gif --every 3
    python recipes/render.py --checkpoint results/train_single/checkpoint_mujoco.pt --out results/single_pnp.gif
    python recipes/render.py --checkpoint <pnp run> --low-level-checkpoint runs/loco --out runs/walking.gif  # on legs

The work is :mod:`pnp.analysis.render_gif` (its docstring says what and how).
"""
from pnp.analysis.render_gif import main


if __name__ == "__main__":
    main()
