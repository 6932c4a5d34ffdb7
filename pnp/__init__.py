"""Collaborative loco-manipulation pick-and-place with a dynamic reward curriculum.

Imports nothing: ``pnp.transforms`` needs only torch, torchrl and tensordict, and the
modules that load mujoco or dm_control set up offscreen rendering themselves
(:mod:`pnp.sim._offscreen`).
"""
