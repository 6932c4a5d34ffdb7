"""Low-level executors: turn HL commands (10 Hz) into actuator controls per physics substep.

:class:`LowLevelExecutor` is the interface a learned LL policy implements later.
:class:`IdealExecutor` is the default: the base tracks the commanded planar velocity
through velocity-actuated planar joints, the arm tracks the commanded EE pose through
batched damped-least-squares IK, and the fingers are position-actuated. Joint targets
advance at the LL rate (50 Hz) and at most at the arm's rated speed (4 rad/s).
"""
from __future__ import annotations

import math
from abc import ABC, abstractmethod

import torch

from pnp.sim.arm_ik import ArmKinematics, clamp_reach, gripper_yaw, wrap_angle
from pnp.sim.robot import ARM_SPEED, FINGER_STROKE

LL_DT = 0.02  # s, LL policy at 50 Hz


class LowLevelExecutor(ABC):
    """Maps HL commands to per-substep controls for every world and robot."""

    @abstractmethod
    def reset(self, worlds: torch.Tensor, arm_q: torch.Tensor) -> None:
        """Forget internal state of ``worlds`` (bool [N]); ``arm_q`` [N, R, 6] is the new pose."""

    @abstractmethod
    def controls(self, command: torch.Tensor, base_yaw: torch.Tensor, arm_q: torch.Tensor, nsub: int, dt: float):
        """Controls for ``nsub`` substeps of ``dt`` seconds.

        ``command`` [N, R, 8] is the clipped HL action. Returns ``(base [N, nsub, R, 3],
        arm [N, nsub, R, 6], fingers [N, nsub, R, 2])``: base velocity in the world frame
        (vx, vy, yaw rate), arm joint targets and finger opening targets.
        """


class IdealExecutor(LowLevelExecutor):
    """``finger_speed`` (m/s per finger, optional): finger targets ramp toward the command at
    this speed. Without it they jump, and the servos drive the pads at up to ~7 m/s: in one
    5 ms substep they pass a 30 mm bar's centre and end crossed inside it (docs/history/pipeline_single.md)."""

    def __init__(self, num_worlds: int, num_robots: int, ik_iters: int = 3, finger_speed: float | None = None):
        if finger_speed is not None and not finger_speed > 0:
            raise ValueError(f"finger_speed must be > 0 (m/s) or None, got {finger_speed!r}")
        self.finger_speed = finger_speed
        self.finger_target = torch.full((num_worlds, num_robots), FINGER_STROKE)
        self.kin = ArmKinematics()
        self.ik_iters = ik_iters
        self.q_target = self.kin.q_default.expand(num_worlds, num_robots, 6).clone()
        # IK is seeded with the previous solution: HL commands change little per step,
        # so a few iterations converge (tested: EE error after one HL step).
        self.q_ik = self.q_target.clone()
        self.yaw_ik = gripper_yaw(self.kin.fk(self.q_ik)[1])  # yaw the last IK aimed for

    def reset(self, worlds, arm_q):
        self.finger_target[worlds] = FINGER_STROKE
        self.q_target[worlds] = arm_q[worlds]
        self.q_ik[worlds] = arm_q[worlds]
        self.yaw_ik[worlds] = gripper_yaw(self.kin.fk(arm_q[worlds])[1])

    def controls(self, command, base_yaw, arm_q, nsub, dt):
        N, R, _ = command.shape
        t = dt * (torch.arange(nsub, dtype=command.dtype) + 0.5)  # mid-substep times
        # Base: body-frame command rotated by the yaw expected at each substep.
        yaw = base_yaw.unsqueeze(1) + command[..., 2].unsqueeze(1) * t[None, :, None]  # [N, nsub, R]
        vx, vy = command[..., 0].unsqueeze(1), command[..., 1].unsqueeze(1)
        c, s = torch.cos(yaw), torch.sin(yaw)
        wz = command[..., 2].unsqueeze(1).expand(N, nsub, R)
        base = torch.stack([vx * c - vy * s, vx * s + vy * c, wz], -1)
        # Arm: IK once per HL step (commands are in the base frame), then a rate-limited ramp.
        # A parallel gripper is symmetric under a half turn: aim for whichever of yaw and
        # yaw + pi is nearer the current one, so the wrist never spins half a turn.
        yaw = command[..., 6]
        yaw = wrap_angle(self.yaw_ik + torch.remainder(yaw - self.yaw_ik + math.pi / 2, math.pi) - math.pi / 2)
        # Near a half turn from the default, flip back so the wrist stays inside its range.
        yaw = torch.where(yaw.abs() > 2.6, yaw - torch.sign(yaw) * math.pi, yaw)
        self.yaw_ik = yaw
        # Targets out of reach go to the nearest reachable point first, as on the kinematic
        # backend: DLS IK on an unreachable target ends wherever its damping lands (measured:
        # a kinematic-trained policy's EE missed its commands by a median 0.44 m on MuJoCo).
        ee = clamp_reach(command[..., 3:6])
        q_ik = self.kin.ik(self.q_ik.reshape(-1, 6), ee.reshape(-1, 3), yaw.reshape(-1), self.ik_iters)
        self.q_ik = q_ik = q_ik.reshape(N, R, 6)
        ticks = torch.floor(t / LL_DT) + 1  # LL ticks elapsed at each substep
        step = (ARM_SPEED * LL_DT * ticks)[None, :, None, None]
        delta = (q_ik - self.q_target).unsqueeze(1)
        arm = self.q_target.unsqueeze(1) + torch.clamp(delta, -step, step)
        self.q_target = arm[:, -1].clone()
        grip = torch.where(command[..., 7] > 0.5, 0.0, FINGER_STROKE)  # closed: squeeze to 0
        if self.finger_speed is None:
            fingers = grip[:, None, :, None].expand(N, nsub, R, 2)
        else:
            reach = (self.finger_speed * dt * torch.arange(1, nsub + 1, dtype=command.dtype))[None, :, None]
            ramp = self.finger_target.unsqueeze(1) + torch.clamp((grip - self.finger_target).unsqueeze(1), -reach, reach)
            self.finger_target = ramp[:, -1].clone()
            fingers = ramp.unsqueeze(-1).expand(N, nsub, R, 2)
        return base, arm, fingers
