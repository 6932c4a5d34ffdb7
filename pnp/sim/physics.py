"""N MuJoCo worlds stepped together with ``mujoco.rollout`` on a persistent thread pool.

No per-world Python in the hot path: one ``Rollout.rollout`` call advances every world
by the HL step's physics substeps, with a control trajectory per world. Each world has
its own ``MjModel`` copy only because box sizes and masses are randomised per world.
"""
from __future__ import annotations

import copy

from pnp.sim import _offscreen  # noqa: F401  # sets MUJOCO_GL before mujoco loads

import mujoco
import numpy as np
from mujoco import rollout

from pnp.sim.box import BoxAsset, box_geometry
from pnp.sim.cores import available_cores

FULL = mujoco.mjtState.mjSTATE_FULLPHYSICS
CTRL = mujoco.mjtState.mjSTATE_CTRL
XFRC = mujoco.mjtState.mjSTATE_XFRC_APPLIED


class BatchedPhysics:
    def __init__(self, model: mujoco.MjModel, num_worlds: int, box_body: int, box_geoms, nthread: int | None = None):
        self.model = model
        self.num_worlds = num_worlds
        self.nthread = nthread or available_cores()
        self.models = [copy.copy(model) for _ in range(num_worlds)]
        self.datas = [mujoco.MjData(model) for _ in range(self.nthread)]
        self._pool = rollout.Rollout(nthread=self.nthread)
        self.nstate = mujoco.mj_stateSize(model, FULL)
        self.state = np.zeros((num_worlds, self.nstate))
        self.sensordata = np.zeros((num_worlds, model.nsensordata))
        self._box_body = box_body
        self._box_geoms = np.asarray(box_geoms)
        self._box_geom_names = [model.geom(int(g)).name for g in self._box_geoms]
        self._pending_xfrc: np.ndarray | None = None
        self._out: tuple[np.ndarray, np.ndarray] | None = None
        self._scratch: mujoco.MjData | None = None  # for forward()
        # Offsets of qpos/qvel/time inside the full-physics state vector.
        self.time_adr = 0
        self.qpos_adr = 1
        self.qvel_adr = 1 + model.nq
        d = mujoco.MjData(model)
        mujoco.mj_getState(model, d, self.state[0], FULL)
        self.state[:] = self.state[0]

    # --- state views -------------------------------------------------------------------
    @property
    def qpos(self) -> np.ndarray:
        return self.state[:, self.qpos_adr : self.qpos_adr + self.model.nq]

    @property
    def qvel(self) -> np.ndarray:
        return self.state[:, self.qvel_adr : self.qvel_adr + self.model.nv]

    @property
    def time(self) -> np.ndarray:
        return self.state[:, self.time_adr]

    def reset_worlds(self, ids: np.ndarray, qpos: np.ndarray) -> None:
        """Put worlds ``ids`` at rest in ``qpos``: zero velocity, time, actuator state."""
        fresh = np.zeros((len(ids), self.nstate))
        fresh[:, self.qpos_adr : self.qpos_adr + self.model.nq] = qpos
        self.state[ids] = fresh
        self.sensordata[ids] = 0.0

    def set_box(self, world: int, asset: BoxAsset) -> None:
        """Resize the box of one world (mass, inertia, geoms) without recompiling."""
        m, b, g = self.models[world], self._box_body, self._box_geoms
        geo = box_geometry(asset, self._box_geom_names)
        m.geom_size[g] = geo["size"]
        m.geom_pos[g] = geo["pos"]
        m.geom_rbound[g] = geo["rbound"]
        m.geom_aabb[g] = geo["aabb"]
        delta = geo["mass"] - m.body_mass[b]
        m.body_mass[b] = geo["mass"]
        m.body_subtreemass[b] += delta
        m.body_subtreemass[0] += delta
        m.body_ipos[b] = geo["com"]
        m.body_iquat[b] = (1.0, 0.0, 0.0, 0.0)
        m.body_inertia[b] = geo["inertia"]

    def push(self, world: int, body: int, wrench: np.ndarray) -> None:
        """Apply an external wrench (force, torque; world frame) during the next step only."""
        if self._pending_xfrc is None:
            self._pending_xfrc = np.zeros((self.num_worlds, self.model.nbody, 6))
        self._pending_xfrc[world, body] = wrench

    def forward(self, ids: np.ndarray) -> None:
        """Recompute the sensors of worlds ``ids`` after their state was edited (``mj_forward``:
        contacts and touch forces of the new configuration; the state itself is unchanged)."""
        if self._scratch is None:  # its own data: the rollout's keep their warm starts
            self._scratch = mujoco.MjData(self.model)
        d = self._scratch
        for w in np.asarray(ids).reshape(-1).tolist():
            mujoco.mj_setState(self.models[w], d, self.state[w], FULL)
            mujoco.mj_forward(self.models[w], d)
            self.sensordata[w] = d.sensordata

    # --- stepping ------------------------------------------------------------------------
    def step(self, ctrl: np.ndarray) -> np.ndarray:
        """Advance all worlds by ``ctrl.shape[1]`` substeps; ``ctrl`` is [N, nsub, nu].

        Returns a bool mask of worlds that diverged (MuJoCo's instability reset, NaN or
        Inf); their state is left as MuJoCo produced it for the caller to reset.
        """
        n, nsub, _ = ctrl.shape
        spec, control = CTRL, ctrl
        if self._pending_xfrc is not None:
            spec = CTRL | XFRC
            xfrc = np.repeat(self._pending_xfrc.reshape(n, 1, -1), nsub, axis=1)
            control = np.concatenate([ctrl, xfrc], axis=-1)
            self._pending_xfrc = None
        t0 = self.time.copy()
        if self._out is None or self._out[0].shape[1] != nsub:
            self._out = (np.empty((n, nsub, self.nstate)), np.empty((n, nsub, self.model.nsensordata)))
        state, sens = self._out
        self._pool.rollout(
            self.models, self.datas, self.state, np.ascontiguousarray(control),
            control_spec=spec, skip_checks=True, nstep=nsub, state=state, sensordata=sens,
        )
        self.state = state[:, -1].copy()
        self.sensordata = sens[:, -1].copy()
        # MuJoCo resets an unstable world to qpos0 and time 0 mid-rollout.
        expected = t0 + nsub * self.model.opt.timestep
        diverged = ~np.isfinite(self.state).all(axis=1) | (np.abs(self.time - expected) > 0.5 * self.model.opt.timestep)
        return diverged

    def close(self) -> None:
        self._pool.close()
