"""Simulation backends behind the PnP environment, and the episode layout they reset to.

A backend owns the physical state of N worlds and exposes it as a :class:`PnPState`.
:class:`MujocoBackend` steps real physics; the kinematic backend (``pnp.kinematic.backend``)
implements the same interface in pure torch.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np
import torch

from pnp.sim.box import BoxAsset
from pnp.sim.executor import IdealExecutor, LowLevelExecutor
from pnp.sim.arm_ik import ArmKinematics
from pnp.sim.physics import BatchedPhysics
from pnp.sim.robot import ARM_DEFAULT, FINGER_STROKE, STANDING_HEIGHT
from pnp.sim.scene import PHYSICS_DT, build_scene
from pnp.task import HL_DT, PnPState, yaw_rotation

BOX_DROP = 0.002  # m: a box is set down this far above the floor, never into it


@dataclass
class Layout:
    """Initial placement for the worlds being reset (rows = those worlds)."""

    base: torch.Tensor  # [M, R, 3] x, y, yaw
    box_xy_yaw: torch.Tensor  # [M, 3]
    box_size: torch.Tensor  # [M, 3] full edges
    box_mass: torch.Tensor  # [M]


class Backend(ABC):
    num_worlds: int
    num_robots: int

    @abstractmethod
    def reset(self, worlds: torch.Tensor, layout: Layout) -> None:
        """Put the worlds ``worlds`` (long indices [M]) at ``layout``, at rest."""

    @abstractmethod
    def step(self, action: torch.Tensor) -> torch.Tensor:
        """Advance one HL step with clipped actions [N, R, 8]; returns diverged bool [N]."""

    @abstractmethod
    def state(self, goal: torch.Tensor, init_goal_dist: torch.Tensor, grasp_cmd: torch.Tensor) -> PnPState:
        """Current state; task quantities the backend does not own are passed in."""

    @abstractmethod
    def get_state(self) -> dict[str, torch.Tensor]:
        """Everything needed to continue bit-for-bit (tensors only; cloned)."""

    @abstractmethod
    def set_state(self, state: dict[str, torch.Tensor]) -> None:
        """Restore what :meth:`get_state` returned."""

    def push(self, world: int, force: np.ndarray) -> None:
        """Apply an external wrench to the box of one world during the next step."""
        raise NotImplementedError(f"{type(self).__name__} does not model external forces")

    def displace_box(self, worlds: torch.Tensor, offsets: torch.Tensor) -> None:
        """Move the boxes of ``worlds`` (distinct long indices [M]) by ``offsets`` [M, 2] (m,
        world frame) and set them down: on the floor, level at their yaw, at rest, out of
        any gripper. Other worlds are untouched."""
        raise NotImplementedError(f"{type(self).__name__} cannot move its box")

    def close(self) -> None:
        pass


class MujocoBackend(Backend):
    """Batched MuJoCo worlds built from the composer scene; physics at 200 Hz."""

    def __init__(self, num_worlds: int, num_robots: int, box: BoxAsset, executor: LowLevelExecutor | None = None,
                 nthread: int | None = None, physics_dt: float = PHYSICS_DT, finger_speed: float | None = None):
        self.num_worlds, self.num_robots = num_worlds, num_robots
        self.mjcf_root, self.model, self.idx = self._build_scene(num_robots, box, physics_dt)
        self.physics = BatchedPhysics(self.model, num_worlds, self.idx.box_body, self.idx.box_geoms, nthread)
        self.executor = executor or IdealExecutor(num_worlds, num_robots, finger_speed=finger_speed)
        self.nsub = int(round(HL_DT / physics_dt))
        self.box_size = torch.tensor(box.size, dtype=torch.float32).repeat(num_worlds, 1)
        self.box_mass = torch.full((num_worlds,), box.mass, dtype=torch.float32)
        self._kin = getattr(self.executor, "kin", None) or ArmKinematics()
        i = self.idx
        self._ctrl_cols = (torch.as_tensor(self._base_ctrl()), torch.as_tensor(i.arm_ctrl), torch.as_tensor(i.finger_ctrl))

    @staticmethod
    def _build_scene(num_robots: int, box: BoxAsset, physics_dt: float):
        return build_scene(num_robots, box, physics_dt)

    def _base_ctrl(self) -> np.ndarray:
        """Actuator columns [R, k] that move each base (the planar joints' velocity servos)."""
        return self.idx.base_ctrl

    def reset(self, worlds, layout):
        m, i = self.model, self.idx
        ids = worlds.cpu().numpy()
        qpos = np.tile(m.qpos0, (len(ids), 1))
        self._place_robots(qpos, layout.base.double().numpy())
        qpos[:, i.arm_qpos.reshape(-1)] = np.tile(ARM_DEFAULT, self.num_robots)
        qpos[:, i.finger_qpos.reshape(-1)] = FINGER_STROKE
        xyz = layout.box_xy_yaw.double().numpy()
        size = layout.box_size.double().numpy()
        b = i.box_qpos
        qpos[:, b : b + 2] = xyz[:, :2]
        qpos[:, b + 2] = size[:, 2] / 2 + BOX_DROP
        qpos[:, b + 3] = np.cos(xyz[:, 2] / 2)
        qpos[:, b + 4 : b + 6] = 0.0
        qpos[:, b + 6] = np.sin(xyz[:, 2] / 2)
        for row, w in enumerate(ids):
            self.physics.set_box(int(w), BoxAsset(tuple(size[row]), float(layout.box_mass[row])))
        self.physics.reset_worlds(ids, qpos)
        self.box_size[worlds] = layout.box_size.float()
        self.box_mass[worlds] = layout.box_mass.float()
        mask = torch.zeros(self.num_worlds, dtype=torch.bool)
        mask[worlds] = True
        self.executor.reset(mask, self._arm_q())

    def _place_robots(self, qpos: np.ndarray, base: np.ndarray) -> None:
        """Write the bases ``base`` [M, R, 3] (x, y, yaw) into the rows ``qpos`` [M, nq]."""
        qpos[:, self.idx.base_qpos.reshape(-1)] = base.reshape(len(qpos), -1)

    def _arm_q(self):
        return torch.from_numpy(self.physics.qpos[:, self.idx.arm_qpos]).float()

    def step(self, action):
        N = self.num_worlds
        base_yaw = torch.from_numpy(self.physics.qpos[:, self.idx.base_qpos[:, 2]]).float()
        base, arm, fingers = self.executor.controls(action, base_yaw, self._arm_q(), self.nsub, self.model.opt.timestep)
        ctrl = torch.zeros(N, self.nsub, self.model.nu, dtype=torch.float64)
        cb, ca, cf = self._ctrl_cols
        ctrl[:, :, cb.reshape(-1)] = base.reshape(N, self.nsub, -1).double()
        ctrl[:, :, ca.reshape(-1)] = arm.reshape(N, self.nsub, -1).double()
        ctrl[:, :, cf.reshape(-1)] = fingers.reshape(N, self.nsub, -1).double()
        return torch.from_numpy(self.physics.step(ctrl.numpy()))

    def get_state(self):
        st = {"physics": torch.from_numpy(self.physics.state.copy()), "sensordata": torch.from_numpy(self.physics.sensordata.copy()),
              "box_size": self.box_size.clone(), "box_mass": self.box_mass.clone()}
        for k in ("q_target", "q_ik", "yaw_ik", "finger_target"):
            if hasattr(self.executor, k):
                st[f"executor.{k}"] = getattr(self.executor, k).clone()
        return st

    def set_state(self, state):
        self.physics.state = state["physics"].numpy().copy()
        self.physics.sensordata = state["sensordata"].numpy().copy()
        self.box_size = state["box_size"].clone()
        self.box_mass = state["box_mass"].clone()
        for w in range(self.num_worlds):
            self.physics.set_box(w, BoxAsset(tuple(self.box_size[w].double().tolist()), float(self.box_mass[w])))
        for k, v in state.items():
            if k.startswith("executor."):
                setattr(self.executor, k.split(".", 1)[1], v.clone())

    def push(self, world, force):
        self.physics.push(world, self.idx.box_body, np.asarray(force, dtype=np.float64))

    def displace_box(self, worlds, offsets):
        ids, b = worlds.cpu().numpy(), self.idx.box_qpos
        qpos, v = self.physics.qpos, self.idx.box_qvel  # views into the batched state
        w, x, y, z = qpos[ids, b + 3 : b + 7].T
        half_yaw = 0.5 * np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))  # a lifted box may tilt: level it
        zero = np.zeros_like(w)
        qpos[ids, b : b + 2] += offsets.double().cpu().numpy()
        qpos[ids, b + 2] = self.box_size[worlds, 2].double().numpy() / 2 + BOX_DROP
        qpos[ids, b + 3 : b + 7] = np.stack([np.cos(half_yaw), zero, zero, np.sin(half_yaw)], -1)
        self.physics.qvel[ids, v : v + 6] = 0.0
        self.physics.forward(ids)  # the pad touch sensors of the new configuration: released

    def state(self, goal, init_goal_dist, grasp_cmd):
        i = self.idx
        qpos = torch.from_numpy(self.physics.qpos).float()
        qvel = torch.from_numpy(self.physics.qvel).float()
        base, base_z, base_vel, origin, rot = self._bases(qpos, qvel)
        arm_q = qpos[:, i.arm_qpos]
        ee_b, ee_rb = self._kin.fk(arm_q)
        b = i.box_qpos
        touch = torch.from_numpy(self.physics.sensordata[:, i.touch]) > 1e-3
        box_rot = quat_to_matrix(qpos[:, b + 3 : b + 7])
        vel = qvel[:, i.box_qvel : i.box_qvel + 6]
        # Free-joint angular velocity is in the body frame: rotate to world.
        box_vel = torch.cat([vel[:, :3], (box_rot @ vel[:, 3:].unsqueeze(-1)).squeeze(-1)], -1)
        return PnPState(
            base=base, base_z=base_z, base_vel=base_vel, arm_q=arm_q, arm_qd=qvel[:, i.arm_qvel],
            finger_q=qpos[:, i.finger_qpos], touch=touch,
            ee_pos=origin + (rot @ ee_b.unsqueeze(-1)).squeeze(-1), ee_rot=rot @ ee_rb,
            box_pos=qpos[:, b : b + 3], box_rot=box_rot, box_vel=box_vel, box_size=self.box_size,
            goal=goal, init_goal_dist=init_goal_dist, grasp_cmd=grasp_cmd,
        )

    def _bases(self, qpos: torch.Tensor, qvel: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Per robot: (x, y, yaw) [N, R, 3], trunk height [N, R], world (vx, vy, yaw rate)
        [N, R, 3], and the trunk frame the arm hangs from: origin [N, R, 3], rotation [N, R, 3, 3]."""
        base = qpos[:, self.idx.base_qpos]
        base_z = torch.full_like(base[..., 0], STANDING_HEIGHT)
        origin = torch.cat([base[..., :2], base_z.unsqueeze(-1)], -1)
        return base, base_z, qvel[:, self.idx.base_qvel], origin, yaw_rotation(base[..., 2])

    def close(self):
        self.physics.close()


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)
