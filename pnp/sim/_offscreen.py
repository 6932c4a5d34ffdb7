"""Offscreen rendering on CPU machines: ``MUJOCO_GL=egl`` unless the user chose a backend.

mujoco and dm_control pick their GL backend once, when first imported, so each pnp module
that loads them imports this one first; ``pnp`` and ``pnp.transforms`` leave the variable
alone. torchrl 0.14 imports mujoco itself when it is installed (``import torchrl.envs``):
a script that renders after importing torchrl sets ``MUJOCO_GL`` at its top, as
``recipes/render.py`` does.
"""
from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")  # Debian's Mesa EGL (OSMesa failed here)
