"""Collaborative loco-manipulation pick-and-place with a dynamic reward curriculum."""
import os

# Offscreen rendering on CPU machines (Debian's Mesa EGL); set before dm_control loads.
os.environ.setdefault("MUJOCO_GL", "egl")
