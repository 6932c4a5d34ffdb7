"""The PnP worlds on legs (issue 24): MuJoCo with floating-base robots whose 12 leg servos
a learned locomotion policy drives in closed loop at 50 Hz.

The high-level action is the same as on the planar robots: base velocity (body frame),
EE pose, gripper. Each HL step (10 Hz) runs ``HL_DT / LL_DT`` low-level ticks; each tick
reads the state, builds every robot's locomotion observation (``pnp.legs.locomotion.observation``:
the HL base velocity as its command), asks the policy for leg actions and steps physics
``LL_DT / PHYSICS_DT`` substeps with the resulting joint targets. The arm and fingers
follow the ideal executor's targets (IK on the trunk frame, rate-limited ramp), as in the
locomotion task the policy was trained on.

A low-level policy is any callable ``observations [M, LOCO_OBS_DIM] -> actions [M, 12]``
(M = worlds x robots, raw units; actions in [-1, 1]); :func:`pnp.training.low_level.load_locomotion_policy`
makes one from a ``task=locomotion`` checkpoint.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import mujoco
import numpy as np
import torch

from pnp.sim.backend import MujocoBackend, quat_to_matrix
from pnp.sim.box import BoxAsset
from pnp.sim.executor import LL_DT
from pnp.legs.locomotion import LOCO_OBS_DIM, STAND, LegServo, base_readouts, observation
from pnp.legs.arm_gravity import ArmGravity
from pnp.sim.robot import ARM_COMPENSATED, ARM_JOINTS, LEG_JOINTS, LEGGED_STAND_HEIGHT
from pnp.sim.scene import PHYSICS_DT, compose_scene
from pnp.task import HL_DT

LowLevelPolicy = Callable[[torch.Tensor], torch.Tensor]


@dataclass
class LeggedSceneIndex:
    """Addresses into qpos/qvel/ctrl/sensordata of the compiled legged scene."""

    base_qpos: np.ndarray  # [robots] start of each trunk's free joint (pos 3, quat 4)
    base_qvel: np.ndarray  # [robots] start of its velocity (lin 3 world, ang 3 body)
    leg_qpos: np.ndarray  # [robots, 12]
    leg_qvel: np.ndarray  # [robots, 12]
    arm_qpos: np.ndarray  # [robots, 6]
    arm_qvel: np.ndarray  # [robots, 6]
    finger_qpos: np.ndarray  # [robots, 2]
    box_qpos: int
    box_qvel: int
    leg_ctrl: np.ndarray  # [robots, 12]
    arm_ctrl: np.ndarray  # [robots, 6]
    arm_ff_ctrl: np.ndarray  # [robots, 6] the arm's gravity feed-forward motors
    finger_ctrl: np.ndarray  # [robots, 2]
    touch: np.ndarray  # [robots, 2]
    box_body: int
    box_geoms: np.ndarray


def build_legged_scene(num_robots: int, box: BoxAsset, physics_dt: float = PHYSICS_DT):
    """The PnP scene with ``Quadruped(legs="actuated")`` robots; returns ``(mjcf_root, model, index)``."""
    root, model = compose_scene(num_robots, box, physics_dt, legs="actuated")
    return root, model, _index(model, num_robots)


def _index(model: mujoco.MjModel, num_robots: int) -> LeggedSceneIndex:
    jq = lambda n: int(model.jnt_qposadr[model.joint(n).id])  # noqa: E731
    jv = lambda n: int(model.jnt_dofadr[model.joint(n).id])  # noqa: E731
    act = lambda n: int(model.actuator(n).id)  # noqa: E731
    R = range(num_robots)
    box_free = model.joint("box/box_free/").id
    box_body = int(model.jnt_bodyid[box_free])
    each = lambda f, names: np.array([[f(f"robot{r}/{n}") for n in names] for r in R])  # noqa: E731
    return LeggedSceneIndex(
        base_qpos=np.array([jq(f"robot{r}/base_free/") for r in R]), base_qvel=np.array([jv(f"robot{r}/base_free/") for r in R]),
        leg_qpos=each(jq, LEG_JOINTS), leg_qvel=each(jv, LEG_JOINTS), arm_qpos=each(jq, ARM_JOINTS),
        arm_qvel=each(jv, ARM_JOINTS), finger_qpos=each(jq, ("finger_l", "finger_r")),
        box_qpos=int(model.jnt_qposadr[box_free]), box_qvel=int(model.jnt_dofadr[box_free]),
        leg_ctrl=each(act, LEG_JOINTS), arm_ctrl=each(act, ARM_JOINTS),
        arm_ff_ctrl=each(act, [f"{n}_ff" for n in ARM_JOINTS]), finger_ctrl=each(act, ("finger_l", "finger_r")),
        touch=np.array([[model.sensor_adr[model.sensor(f"robot{r}/pad_{s}_touch").id] for s in "lr"] for r in R]),
        box_body=box_body, box_geoms=np.array([g for g in range(model.ngeom) if model.geom_bodyid[g] == box_body]),
    )


class LeggedMujocoBackend(MujocoBackend):
    """:class:`pnp.sim.backend.MujocoBackend` on legs, the legs driven by ``policy`` (see module doc)."""

    def __init__(self, num_worlds: int, num_robots: int, box: BoxAsset, policy: LowLevelPolicy,
                 nthread: int | None = None, physics_dt: float = PHYSICS_DT, finger_speed: float | None = None,
                 servo: LegServo = LegServo()):
        # Set before the scene is built: the physics copies the model once per world, so gains
        # written into ``self.model`` afterwards would never reach the simulated servos.
        self.policy, self.servo = policy, servo  # the servo the leg policy was trained under
        super().__init__(num_worlds, num_robots, box, nthread=nthread, physics_dt=physics_dt, finger_speed=finger_speed)
        self.decimation = int(round(LL_DT / physics_dt))
        if self.nsub % self.decimation:
            raise ValueError(f"HL step {HL_DT} s is not a whole number of LL ticks of {LL_DT} s at dt={physics_dt}")
        self.last_leg_action = torch.zeros(num_worlds, num_robots, len(LEG_JOINTS))
        self.arm_gravity = [ArmGravity(self.model, f"robot{r}/", int(self.idx.base_qpos[r]), ARM_COMPENSATED, ARM_JOINTS)
                            for r in range(num_robots)]

    def _build_scene(self, num_robots, box, physics_dt):
        root, model, idx = build_legged_scene(num_robots, box, physics_dt)
        self.servo.apply(model, idx.leg_ctrl)
        return root, model, idx

    def _base_ctrl(self):
        return self.idx.leg_ctrl  # the legs move the base

    def _place_robots(self, qpos, base):
        adr = self.idx.base_qpos
        qpos[:, adr] = base[..., 0]
        qpos[:, adr + 1] = base[..., 1]
        qpos[:, adr + 2] = LEGGED_STAND_HEIGHT
        qpos[:, adr + 3] = np.cos(base[..., 2] / 2)
        qpos[:, adr + 4] = 0.0
        qpos[:, adr + 5] = 0.0
        qpos[:, adr + 6] = np.sin(base[..., 2] / 2)

    def reset(self, worlds, layout):
        super().reset(worlds, layout)
        self.last_leg_action[worlds] = 0.0

    def _read(self) -> tuple[torch.Tensor, torch.Tensor]:
        return torch.from_numpy(self.physics.qpos).float(), torch.from_numpy(self.physics.qvel).float()

    def leg_observations(self, command: torch.Tensor) -> torch.Tensor:
        """Every robot's locomotion observation [N, R, LOCO_OBS_DIM] under HL ``command`` [N, R, 8]."""
        qpos, qvel = self._read()
        i, obs = self.idx, []
        for r in range(self.num_robots):
            base = base_readouts(qpos, qvel, int(i.base_qpos[r]), int(i.base_qvel[r]))
            obs.append(observation(base, command[:, r, :3], qpos[:, i.leg_qpos[r]], qvel[:, i.leg_qvel[r]],
                                   self.last_leg_action[:, r], qpos[:, i.arm_qpos[r]])[:, 0])
        return torch.stack(obs, 1)

    def step(self, action):
        N, R, i = self.num_worlds, self.num_robots, self.idx
        qpos, qvel = self._read()
        yaw = self._bases(qpos, qvel)[0][..., 2]
        _, arm, fingers = self.executor.controls(action, yaw, qpos[:, i.arm_qpos], self.nsub, self.model.opt.timestep)
        diverged = np.zeros(N, dtype=bool)
        ctrl = np.zeros((N, self.decimation, self.model.nu))
        for tick in range(self.nsub // self.decimation):
            obs = self.leg_observations(action)
            leg_action = self.policy(obs.reshape(N * R, LOCO_OBS_DIM)).reshape(N, R, len(LEG_JOINTS))
            if not torch.isfinite(leg_action).all():
                raise ValueError("the low-level policy returned non-finite leg actions")
            leg_action = leg_action.clamp(-1.0, 1.0)
            self.last_leg_action = leg_action.detach().clone()
            sub = slice(tick * self.decimation, (tick + 1) * self.decimation)
            target = self.servo.targets(leg_action.reshape(N * R, -1)) - STAND
            ctrl[:, :, i.leg_ctrl.reshape(-1)] = target.reshape(N, 1, -1).double().numpy()
            ctrl[:, :, i.arm_ctrl.reshape(-1)] = arm[:, sub].reshape(N, self.decimation, -1).double().numpy()
            ctrl[:, :, i.finger_ctrl.reshape(-1)] = fingers[:, sub].reshape(N, self.decimation, -1).double().numpy()
            for r, gravity in enumerate(self.arm_gravity):  # held for the tick, as a controller's update
                ctrl[:, :, i.arm_ff_ctrl[r]] = gravity.torques(self.physics.qpos)[:, None]
            diverged |= self.physics.step(ctrl)
        return torch.from_numpy(diverged)

    def get_state(self):
        return {**super().get_state(), "last_leg_action": self.last_leg_action.clone()}

    def set_state(self, state):
        super().set_state(state)
        self.last_leg_action = state["last_leg_action"].clone()

    def _bases(self, qpos, qvel):
        adr, dof = self.idx.base_qpos, self.idx.base_qvel
        pos = torch.stack([qpos[:, a : a + 3] for a in adr], 1)  # [N, R, 3]
        quat = torch.stack([qpos[:, a + 3 : a + 7] for a in adr], 1)
        rot = quat_to_matrix(quat)  # trunk to world
        lin = torch.stack([qvel[:, d : d + 3] for d in dof], 1)
        ang = (rot @ torch.stack([qvel[:, d + 3 : d + 6] for d in dof], 1).unsqueeze(-1)).squeeze(-1)  # body -> world
        yaw = torch.atan2(rot[..., 1, 0], rot[..., 0, 0])
        base = torch.stack([pos[..., 0], pos[..., 1], yaw], -1)
        return base, pos[..., 2], torch.stack([lin[..., 0], lin[..., 1], ang[..., 2]], -1), pos, rot
