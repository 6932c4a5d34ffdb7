"""Offscreen rendering of one world of a :class:`pnp.sim.backend.MujocoBackend` (CPU: EGL/Mesa)."""
from __future__ import annotations

from pnp.sim import _offscreen  # noqa: F401  # sets MUJOCO_GL before mujoco loads

import mujoco
import numpy as np

from pnp.sim.physics import FULL


class WorldRenderer:
    def __init__(self, backend, world: int = 0, width: int = 480, height: int = 360):
        self.backend, self.world = backend, world
        self.model = backend.physics.models[world]
        self.data = mujoco.MjData(self.model)
        self.renderer = mujoco.Renderer(self.model, height=height, width=width)
        self.camera = mujoco.MjvCamera()
        self.camera.type = mujoco.mjtCamera.mjCAMERA_FREE
        self.camera.distance, self.camera.elevation, self.camera.azimuth = 4.5, -30.0, 120.0

    def frame(self, goal_xy=(0.0, 0.0), track: bool = True) -> np.ndarray:
        """RGB uint8 [H, W, 3] of the world's current state; the camera follows the box."""
        mujoco.mj_setState(self.model, self.data, self.backend.physics.state[self.world], FULL)
        self.data.mocap_pos[0, :2] = goal_xy
        mujoco.mj_forward(self.model, self.data)
        if track:
            b = self.backend.idx.box_qpos
            box = self.data.qpos[b : b + 3]
            self.camera.lookat[:] = 0.5 * (box + np.array([*goal_xy, 0.0]))
            self.camera.lookat[2] = 0.3
        self.renderer.update_scene(self.data, self.camera)
        return self.renderer.render()

    def close(self):
        self.renderer.close()
