"""A fast kinematic backend of the PnP environment, in pure batched torch (``backend="kinematic"``).

It implements :class:`pnp.backend.Backend` with no physics engine: every quantity is a
closed-form update of float32 tensors over all worlds and robots at once (no Python loop
over worlds). It produces the same :class:`pnp.task.PnPState` as the MuJoCo backend, so
actions, observations, reward terms, stage conditions and the success/fall/timeout rules
(all computed by ``pnp.task`` and ``envs.pnp_env``) are shared unchanged.

Model, per HL step of ``HL_DT`` = 0.1 s:

* **Base**: the commanded body-frame planar velocity (vx, vy) and yaw rate are tracked
  instantly and integrated exactly (constant twist over the step: arc integration). The
  trunk stays at ``STANDING_HEIGHT``. ``base_vel`` is the world-frame velocity at the end
  of the step.
* **Arm / EE**: the commanded EE position and yaw (base frame, downward gripper) are
  followed with a first-order lag of time constant ``ee_tau`` (default 0.08 s, i.e. 71 %
  of the remaining error is closed per HL step; discretised exactly). Like the MuJoCo
  executor, the gripper aims for whichever of yaw and yaw + pi is nearer its current yaw
  (a parallel gripper is symmetric under a half turn). The lagged target is clamped to
  the arm's reach (wrist centre within ``REACH_MAX`` of the shoulder, and not closer than
  ``REACH_MIN``), then turned into joint angles by **closed-form IK** of the DynaArm-like
  chain for a downward gripper (j1 yaw, j2/j3 two-link planar solve on the elbow branch
  the joint ranges allow, j5 = pi/2 - j2 - j3 so the gripper points down, j4 = 0,
  j6 = j1 - yaw). This is exact for a downward gripper (tests compare it with
  ``ArmKinematics.fk``) and costs ~20 elementwise ops, against ~1 ms per 1024 rows per
  iteration for the DLS ``ArmKinematics.ik`` the MuJoCo executor runs (measured: 3
  warm-started DLS iterations alone would take more than the whole step budget).
  Joint targets are then rate-limited to ``ARM_SPEED`` (4 rad/s, as the executor does)
  and clamped to ``ARM_RANGES``; the EE pose reported is the closed-form FK of the joint
  angles, so ``arm_q``, ``ee_pos`` and ``ee_rot`` are always mutually consistent.
  ``arm_qd`` is the finite difference of ``arm_q`` over the step.
* **Fingers**: the opening of both fingers moves toward 0 (command > 0.5) or
  ``FINGER_STROKE`` at ``finger_speed`` (default 0.5 m/s: a full stroke in 0.14 s).
  When closing fingers reach the bar radius while the EE is within ``GRASP_DIST`` of a
  handle bar ("its" handle, the one whose centre is nearest, as ``pnp.task.geometry``
  picks it) and the closing axis is within ``GRASP_ALIGN`` of perpendicular to the bar,
  the handle is grasped: fingers stop at ``HANDLE_RADIUS`` and both pads report touch.
  Fingers that closed on nothing cannot grasp until they open again.
* **Grasped box**: moves rigidly with the grasping gripper, keeping the relative pose
  (position and yaw in the gripper's yaw frame) of grasp time. The grasp is kept while
  the command stays closed and the EE stays within ``GRASP_DIST`` of its bar (else the
  handle slips out and the fingers close on nothing).
* **Two robots** (heavy box): the box moves only while both robots hold different
  handles; its pose is then the mean of the two poses implied by the grippers (circular
  mean for yaw), and a robot whose EE drifts more than ``GRASP_DIST`` from its bar loses
  its grasp. With a single holder the box does not move at all (no sliding, no
  rotation, no tilting: our choice); the holder keeps its grasp only while its EE stays
  within ``GRASP_DIST`` of the bar.
* **Free box**: falls under gravity (exact constant-acceleration update of z and vz,
  horizontal velocity kept while airborne), stops on the floor with zero velocity and
  rests there. A carried box cannot be pushed through the floor: the holder's EE height
  is clamped so the box bottom stays at or above z = 0.
* ``box_vel`` (world linear and angular velocity) is the finite difference of the box
  pose over the HL step.

Simplifications (with respect to the MuJoCo backend):

* No contacts at all: bases, legs, arm and gripper pass through the box and through each
  other; the box is never pushed, only carried. (The env's collision *term* is a
  geometric proxy computed by ``pnp.task`` and still works.)
* The box never tilts or swings: it stays level (yaw only), also when hanging from one
  handle, and it never slips in the pads. It never leaves the floor unless carried.
* The base never falls (``base_z`` is always ``STANDING_HEIGHT``), so the fall term and
  fall termination never fire; the base has no acceleration limits and no legs.
* The wrist roll j4 is always 0 (the closed-form IK branch); the EE lag replaces the
  executor's per-joint PD/rate dynamics at 50 Hz; no IK failure modes.
* Box mass is stored but only matters through the dual-robot "heavy box" rule.
* ``push`` (external wrenches) is not modelled (``NotImplementedError``). The backend
  never diverges (``step`` returns all False).
"""
from __future__ import annotations

import math

import torch

from pnp.backend import Backend, Layout
from pnp.box import HANDLE_HEIGHT, HANDLE_INSET, HANDLE_LEN, HANDLE_RADIUS
from pnp.robot import (
    ARM_DEFAULT, ARM_MOUNT, ARM_RANGES, ARM_SPEED, FINGER_STROKE, FOREARM, GRIPPER_LEN, SHOULDER_HEIGHT,
    STANDING_HEIGHT, UPPER_ARM, WRIST,
)
from pnp.task import GRASP_DIST, HL_DT, PnPState

GRAVITY = 9.81  # m/s^2
EE_TAU = 0.08  # s, first-order lag of the EE toward its commanded pose
FINGER_SPEED = 0.5  # m/s per finger
GRASP_ALIGN = 0.7  # grasp needs 1 - |cos(closing axis, bar axis)| above this (~17 deg)
L1, L2 = UPPER_ARM, FOREARM  # shoulder (j2) -> elbow (j3) -> wrist pitch (j5)
LW = WRIST + GRIPPER_LEN  # wrist pitch (j5) -> EE site, along the gripper's approach axis
SHOULDER = (ARM_MOUNT[0], ARM_MOUNT[1], ARM_MOUNT[2] + SHOULDER_HEIGHT)  # j2 in the base frame
_J3_MAX = ARM_RANGES[2][1]  # the elbow never straightens fully
REACH_MAX = 0.995 * math.sqrt(L1 * L1 + L2 * L2 + 2 * L1 * L2 * math.cos(_J3_MAX))
REACH_MIN = 0.25  # m, ours: keeps the wrist clear of the shoulder
_Q6_WIND = ARM_RANGES[5][1] - 0.1  # flip the gripper's half-turn choice before j6 reaches its limit


def arm_fk(q: torch.Tensor, base_yaw: torch.Tensor | None = None):
    """Closed-form FK of the EE site for j4 = 0: position [..., 3] (base frame) and the
    rotation [..., 3, 3] in the frame yawed by ``base_yaw`` (base frame when None)."""
    q1, q2, q3, q5, q6 = q[..., 0], q[..., 1], q[..., 2], q[..., 4], q[..., 5]
    a3 = q2 + q3
    a5 = a3 + q5
    r = L1 * torch.cos(q2) + L2 * torch.cos(a3) + LW * torch.cos(a5)
    c1, s1 = torch.cos(q1), torch.sin(q1)
    z = SHOULDER[2] - L1 * torch.sin(q2) - L2 * torch.sin(a3) - LW * torch.sin(a5)
    pos = torch.stack([SHOULDER[0] + r * c1, SHOULDER[1] + r * s1, z], -1)
    psi = q1 if base_yaw is None else q1 + base_yaw
    return pos, _zyx_rotation(psi, a5, q6)


def _zyx_rotation(psi, beta, gamma):
    """Rz(psi) Ry(beta) Rx(gamma), batched."""
    cp, sp = torch.cos(psi), torch.sin(psi)
    cb, sb = torch.cos(beta), torch.sin(beta)
    cg, sg = torch.cos(gamma), torch.sin(gamma)
    row0 = torch.stack([cp * cb, cp * sb * sg - sp * cg, cp * sb * cg + sp * sg], -1)
    row1 = torch.stack([sp * cb, sp * sb * sg + cp * cg, sp * sb * cg - cp * sg], -1)
    row2 = torch.stack([-sb, cb * sg, cb * cg], -1)
    return torch.stack([row0, row1, row2], -2)


def clamp_reach(ee: torch.Tensor) -> torch.Tensor:
    """EE positions [..., 3] (base frame, downward gripper) moved into the arm's reach."""
    sh = torch.tensor(SHOULDER, dtype=ee.dtype, device=ee.device)
    w = ee - sh
    w = torch.cat([w[..., :2], w[..., 2:] + LW], -1)  # wrist centre relative to the shoulder
    n = w.norm(dim=-1, keepdim=True)
    w = w * (n.clamp(REACH_MIN, REACH_MAX) / n.clamp(min=1e-6))
    return torch.cat([w[..., :2], w[..., 2:] - LW], -1) + sh


def arm_ik(ee: torch.Tensor, yaw: torch.Tensor) -> torch.Tensor:
    """Closed-form IK [..., 6] for an EE at ``ee`` (base frame, within reach) pointing
    down with gripper yaw ``yaw`` (as in ``pnp.kinematics.gripper_down_rotation``)."""
    dx, dy = ee[..., 0] - SHOULDER[0], ee[..., 1] - SHOULDER[1]
    q1 = torch.atan2(dy, dx)
    dr = torch.sqrt(dx * dx + dy * dy)
    dz = ee[..., 2] + LW - SHOULDER[2]
    d2 = dr * dr + dz * dz
    c3 = ((d2 - L1 * L1 - L2 * L2) / (2 * L1 * L2)).clamp(-1.0, 1.0)
    q3 = -torch.acos(c3)  # the elbow branch the joint range allows (j3 < 0)
    psi = torch.atan2(-dz, dr)  # wrist centre's angle below the horizontal
    q2 = psi - torch.atan2(L2 * torch.sin(q3), L1 + L2 * torch.cos(q3))
    q5 = math.pi / 2 - q2 - q3
    q6 = q1 - yaw
    return torch.stack([q1, q2, q3, torch.zeros_like(q1), q5, q6], -1)


def _rot2(yaw: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate the xy part of ``v`` [..., 3 or 2] by ``yaw`` [...]."""
    c, s = torch.cos(yaw), torch.sin(yaw)
    x, y = v[..., 0], v[..., 1]
    out = [c * x - s * y, s * x + c * y]
    if v.shape[-1] == 3:
        out.append(v[..., 2])
    return torch.stack(out, -1)


def _wrap(a: torch.Tensor) -> torch.Tensor:
    return torch.remainder(a + math.pi, 2 * math.pi) - math.pi


class KinematicBackend(Backend):
    """Kinematic PnP worlds in pure torch; see the module docstring for the model."""

    def __init__(self, num_worlds: int, num_robots: int, ee_tau: float = EE_TAU, finger_speed: float = FINGER_SPEED,
                 dt: float = HL_DT, grasp_dist: float = GRASP_DIST, grasp_align: float = GRASP_ALIGN):
        if num_robots not in (1, 2):
            raise ValueError(f"num_robots must be 1 or 2, got {num_robots!r}")
        self.num_worlds, self.num_robots = N, R = num_worlds, num_robots
        self.dt = float(dt)
        self.ee_alpha = 1.0 - math.exp(-self.dt / ee_tau) if ee_tau > 0 else 1.0
        self.finger_step = finger_speed * self.dt
        self.grasp_dist, self.grasp_align = grasp_dist, grasp_align
        f = dict(dtype=torch.float32)
        lim = torch.tensor(ARM_RANGES, **f)
        self.q_low, self.q_high = lim[:, 0], lim[:, 1]
        self.q_default = torch.tensor(ARM_DEFAULT, **f)
        self.dq_max = ARM_SPEED * self.dt
        # Robot state.
        self.base = torch.zeros(N, R, 3, **f)  # x, y, yaw (world)
        self.base_vel = torch.zeros(N, R, 3, **f)
        self.arm_q = self.q_default.expand(N, R, 6).clone()
        self.arm_qd = torch.zeros(N, R, 6, **f)
        self.finger = torch.full((N, R), FINGER_STROKE, **f)  # opening of each finger
        self.grasp = torch.zeros(N, R, dtype=torch.bool)  # holding its handle
        self.handle_idx = torch.zeros(N, R, dtype=torch.long)  # which handle is held (0: +x, 1: -x)
        self.rel = torch.zeros(N, R, 4, **f)  # box pose in the gripper's yaw frame at grasp: xyz, yaw
        # Box state (always level: position and yaw).
        self.box_pos = torch.zeros(N, 3, **f)
        self.box_yaw = torch.zeros(N, **f)
        self.box_v = torch.zeros(N, 3, **f)  # velocity while airborne
        self.box_vel = torch.zeros(N, 6, **f)  # finite-difference velocity (reported)
        self.box_size = torch.ones(N, 3, **f)
        self.box_mass = torch.ones(N, **f)
        self._update_arm_cache()

    # --- Backend API -----------------------------------------------------------------------
    def reset(self, worlds: torch.Tensor, layout: Layout) -> None:
        w = worlds.long()
        self.base[w] = layout.base.float()
        self.base_vel[w] = 0.0
        self.arm_q[w] = self.q_default
        self.arm_qd[w] = 0.0
        self.finger[w] = FINGER_STROKE
        self.grasp[w] = False
        self.handle_idx[w] = 0
        self.rel[w] = 0.0
        size = layout.box_size.float()
        xyz = layout.box_xy_yaw.float()
        self.box_pos[w] = torch.cat([xyz[:, :2], size[:, 2:] / 2], -1)
        self.box_yaw[w] = xyz[:, 2]
        self.box_v[w] = 0.0
        self.box_vel[w] = 0.0
        self.box_size[w] = size
        self.box_mass[w] = layout.box_mass.float()
        self._update_arm_cache()

    def step(self, action: torch.Tensor) -> torch.Tensor:
        dt = self.dt
        action = action.float()
        # Base: constant body-frame twist over the step, integrated exactly.
        v, wz = action[..., :2], action[..., 2]
        yaw0 = self.base[..., 2]
        dyaw = wz * dt
        mid = yaw0 + 0.5 * dyaw
        disp = _rot2(mid, v) * (dt * torch.sinc(dyaw / (2 * math.pi))).unsqueeze(-1)
        yaw1 = _wrap(yaw0 + dyaw)
        self.base = torch.cat([self.base[..., :2] + disp, yaw1.unsqueeze(-1)], -1)
        self.base_vel = torch.cat([_rot2(yaw1, v), wz.unsqueeze(-1)], -1)

        # Grasp release: opening the gripper lets go.
        closed = action[..., 7] > 0.5
        grasp = self.grasp & closed

        # EE: first-order lag toward the command (base frame), reach clamp, floor clamp.
        ee_yaw_now = self._ee_yaw_b
        yaw_cmd = action[..., 6]
        yaw_cmd = ee_yaw_now + torch.remainder(yaw_cmd - ee_yaw_now + math.pi / 2, math.pi) - math.pi / 2
        # ... unless that would wind the wrist roll j6 (= j1 - yaw) past its range.
        q6_cmd = self.arm_q[..., 0] - yaw_cmd
        yaw_cmd = yaw_cmd + math.pi * ((q6_cmd > _Q6_WIND).float() - (q6_cmd < -_Q6_WIND).float())
        a = self.ee_alpha
        ee_t = self._ee_b + a * (action[..., 3:6] - self._ee_b)
        yaw_t = ee_yaw_now + a * (yaw_cmd - ee_yaw_now)
        ee_t = clamp_reach(ee_t)
        # A held box stays above the floor: EE height >= c/2 - (box z - EE z at grasp).
        min_z = (self.box_size[:, 2:3] / 2 - self.rel[..., 2]) - STANDING_HEIGHT
        ee_z = torch.where(grasp, torch.maximum(ee_t[..., 2], min_z), ee_t[..., 2])
        ee_t = torch.cat([ee_t[..., :2], ee_z.unsqueeze(-1)], -1)
        q_des = arm_ik(ee_t, yaw_t)
        q_old = self.arm_q
        q = q_old + (q_des - q_old).clamp(-self.dq_max, self.dq_max)
        self.arm_q = q = torch.maximum(torch.minimum(q, self.q_high), self.q_low)
        self.arm_qd = (q - q_old) / dt
        self._update_arm_cache()
        ee_w, g_yaw = self.ee_pos, self._ee_yaw_w

        # Box: carried, resting or falling.
        pos0, yaw_b0 = self.box_pos, self.box_yaw
        implied_pos = ee_w + _rot2(g_yaw, self.rel[..., :3])  # [N, R, 3]
        implied_yaw = g_yaw + self.rel[..., 3]
        half_c = self.box_size[:, 2] / 2
        if self.num_robots == 1:
            carried = grasp[:, 0]
            new_pos, new_yaw = implied_pos[:, 0], implied_yaw[:, 0]
        else:
            carried = grasp.all(-1) & (self.handle_idx[:, 0] != self.handle_idx[:, 1])
            new_pos = implied_pos.mean(1)
            new_yaw = torch.atan2(torch.sin(implied_yaw).sum(-1), torch.cos(implied_yaw).sum(-1))
        # Free fall of an unsupported box (exact under constant acceleration), landing.
        airborne = pos0[:, 2] > half_c + 1e-6
        vz = self.box_v[:, 2]
        z_fall = pos0[:, 2] + vz * dt - 0.5 * GRAVITY * dt * dt
        landed = z_fall <= half_c
        v_free = torch.where((airborne & ~landed).unsqueeze(-1),
                             torch.cat([self.box_v[:, :2], (vz - GRAVITY * dt).unsqueeze(-1)], -1), torch.zeros_like(self.box_v))
        xy_free = pos0[:, :2] + torch.where(airborne.unsqueeze(-1), self.box_v[:, :2] * dt, torch.zeros_like(pos0[:, :2]))
        free_pos = torch.cat([xy_free, torch.where(airborne, z_fall.clamp(min=0.0), pos0[:, 2]).clamp(min=half_c).unsqueeze(-1)], -1)
        c3 = carried.unsqueeze(-1)
        new_pos = torch.where(c3, new_pos, free_pos)
        new_pos = torch.cat([new_pos[:, :2], torch.maximum(new_pos[:, 2], half_c).unsqueeze(-1)], -1)
        self.box_pos = new_pos
        self.box_yaw = torch.where(carried, _wrap(new_yaw), yaw_b0)
        lin = (new_pos - pos0) / dt
        self.box_v = torch.where(c3, lin, v_free)
        self.box_vel = torch.cat([lin, torch.zeros_like(lin[:, :2]), (_wrap(self.box_yaw - yaw_b0) / dt).unsqueeze(-1)], -1)

        # Grasps: kept while the EE stays on its bar; new ones when the fingers reach a bar.
        k_near, bar_d, align = self._bars(ee_w, g_yaw)
        d_held = torch.gather(bar_d, 2, self.handle_idx.unsqueeze(-1)).squeeze(-1)
        grasp = grasp & (d_held < self.grasp_dist)
        d_near = torch.gather(bar_d, 2, k_near.unsqueeze(-1)).squeeze(-1)
        target = torch.where(closed, 0.0, FINGER_STROKE)
        f0 = self.finger
        f1 = f0 + (target - f0).clamp(-self.finger_step, self.finger_step)
        reach_bar = closed & (f0 > HANDLE_RADIUS) & (f1 <= HANDLE_RADIUS)
        new = reach_bar & ~grasp & (d_near < self.grasp_dist) & (align > self.grasp_align)
        if bool(new.any()):
            self._attach(new, k_near, ee_w, g_yaw)
        self.grasp = grasp = grasp | new
        self.finger = torch.where(grasp, torch.full_like(f1, HANDLE_RADIUS), f1)
        return torch.zeros(self.num_worlds, dtype=torch.bool)

    def state(self, goal: torch.Tensor, init_goal_dist: torch.Tensor, grasp_cmd: torch.Tensor) -> PnPState:
        touch = self.grasp.unsqueeze(-1).expand(-1, -1, 2)
        return PnPState(
            base=self.base, base_z=self._base_z, base_vel=self.base_vel, arm_q=self.arm_q, arm_qd=self.arm_qd,
            finger_q=self.finger.unsqueeze(-1).expand(-1, -1, 2), touch=touch, ee_pos=self.ee_pos, ee_rot=self.ee_rot,
            box_pos=self.box_pos, box_rot=self._box_rot(), box_vel=self.box_vel, box_size=self.box_size,
            goal=goal, init_goal_dist=init_goal_dist, grasp_cmd=grasp_cmd,
        )

    _STATE = ("base", "base_vel", "arm_q", "arm_qd", "finger", "grasp", "handle_idx", "rel", "box_pos", "box_yaw",
              "box_v", "box_vel", "box_size", "box_mass")

    def get_state(self) -> dict[str, torch.Tensor]:
        return {k: getattr(self, k).clone() for k in self._STATE}

    def set_state(self, state: dict[str, torch.Tensor]) -> None:
        missing = [k for k in self._STATE if k not in state]
        if missing:
            raise KeyError(f"kinematic backend state is missing {missing}")
        for k in self._STATE:
            setattr(self, k, state[k].clone())
        self._update_arm_cache()

    # --- internals ---------------------------------------------------------------------------
    def _update_arm_cache(self):
        """World EE pose and gripper yaws from the arm joints and the base."""
        base = self.base
        ee_b, self.ee_rot = arm_fk(self.arm_q, base[..., 2])
        self._ee_b = ee_b
        # Gripper yaw (pnp.kinematics.gripper_yaw) of a downward gripper, unwrapped so that
        # j6 = j1 - yaw stays continuous (exact while j5 keeps the gripper vertical).
        self._ee_yaw_b = self.arm_q[..., 0] - self.arm_q[..., 5]
        self._ee_yaw_w = self._ee_yaw_b + base[..., 2]
        self._base_z = torch.full_like(base[..., 0], STANDING_HEIGHT)
        w = _rot2(base[..., 2], ee_b)
        self.ee_pos = torch.cat([base[..., :2] + w[..., :2], (w[..., 2] + STANDING_HEIGHT).unsqueeze(-1)], -1)

    def _box_rot(self):
        c, s = torch.cos(self.box_yaw), torch.sin(self.box_yaw)
        z, o = torch.zeros_like(c), torch.ones_like(c)
        return torch.stack([c, -s, z, s, c, z, z, z, o], -1).view(-1, 3, 3)

    def _bars(self, ee_w, g_yaw):
        """Nearest handle by centre distance [N, R], EE distance to both bars [N, R, 2], and
        the gripper/bar alignment [N, R] (``pnp.task.geometry``'s definitions)."""
        size = self.box_size
        d = ee_w - self.box_pos.unsqueeze(1)
        local = _rot2(-self.box_yaw.unsqueeze(1), d)  # EE in the (level) box frame, [N, R, 3]
        hx = (size[:, 0] / 2 - HANDLE_INSET).view(-1, 1, 1)
        hz = (size[:, 2] / 2 + HANDLE_HEIGHT).view(-1, 1)
        half_len = (0.6 * size[:, 1]).clamp(max=HANDLE_LEN).view(-1, 1, 1) / 2
        sign = torch.tensor([1.0, -1.0], dtype=d.dtype)
        dx = local[..., :1] - sign * hx  # [N, R, 2]
        dy = local[..., 1:2]
        dz = (local[..., 2] - hz).unsqueeze(-1)
        centre = dx * dx + dy * dy + dz * dz
        excess = (dy.abs() - half_len).clamp(min=0.0)
        bar = torch.sqrt(dx * dx + dz * dz + excess * excess)
        k = (centre[..., 1] < centre[..., 0]).long()
        # Closing axis (-sin, cos) of the gripper yaw against the bar axis (box y).
        align = 1.0 - torch.cos(g_yaw - self.box_yaw.unsqueeze(1)).abs()
        return k, bar, align

    def _attach(self, new, k, ee_w, g_yaw):
        """Record the box pose relative to the gripper for robots that just grasped."""
        d = self.box_pos.unsqueeze(1) - ee_w
        rel = torch.cat([_rot2(-g_yaw, d), (self.box_yaw.unsqueeze(1) - g_yaw).unsqueeze(-1)], -1)
        self.rel = torch.where(new.unsqueeze(-1), rel, self.rel)
        self.handle_idx = torch.where(new, k, self.handle_idx)
