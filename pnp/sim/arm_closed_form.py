"""Closed-form kinematics of the DynaArm-like arm with a downward gripper (wrist roll j4 = 0):
FK, IK and the reachable shell of the wrist centre, exact for a downward gripper (tests
compare them with ``pnp.sim.arm_ik.ArmKinematics.fk``). The kinematic backend
(``pnp.kinematic.backend``, whose docstring says why closed form) moves its arms with these.

:func:`arm_fk` and :func:`arm_ik` are the plain forms; :func:`arm_fk_columns`,
:func:`wrist_in_reach` and :func:`ik_wrist` the same maths on structure-of-arrays columns,
as the backend's step uses them (``pnp.kinematic.step`` says why).
"""
from __future__ import annotations

import math

import torch

from pnp.sim.arm_ik import L1, L2, LW, REACH_MAX, REACH_MIN, SHOULDER
from pnp.sim.robot import STANDING_HEIGHT

EE_TO_WRIST = torch.tensor([-SHOULDER[0], -SHOULDER[1], LW - SHOULDER[2]])  # EE -> wrist centre rel. to the shoulder


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


def arm_ik(ee: torch.Tensor, yaw: torch.Tensor) -> torch.Tensor:
    """Closed-form IK [..., 6] for an EE at ``ee`` (base frame, within reach) pointing
    down with gripper yaw ``yaw`` (as in ``pnp.sim.arm_ik.gripper_down_rotation``)."""
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


def wrap_angle(a: torch.Tensor) -> torch.Tensor:
    """Angles wrapped into [-pi, pi)."""
    return torch.remainder(a + math.pi, 2 * math.pi) - math.pi


def arm_fk_columns(q: torch.Tensor, yaw: torch.Tensor, bx: torch.Tensor, by: torch.Tensor) -> dict[str, torch.Tensor]:
    """Closed-form FK (as :func:`arm_fk`) of joints ``q`` [N, R, 6] on bases at (bx, by, yaw):
    EE in the base frame [N, R, 3], EE in the world, its rotation [N, R, 3, 3], and
    cos/sin of the base yaw and of the gripper yaw (world)."""
    q1, q2, q3, _, q5, q6 = q.unbind(-1)
    a3 = q2 + q3
    a5 = a3 + q5
    psi = q1 + yaw
    ang = torch.stack([q1, q2, a3, a5, psi, q6, yaw])
    c1, c2, c3, cb, cp, cg, cy = torch.cos(ang).unbind(0)
    s1, s2, s3, sb, sp, sg, sy = torch.sin(ang).unbind(0)
    r = torch.add(torch.add(c2 * L1, c3, alpha=L2), cb, alpha=LW)
    z = torch.add(torch.add(s2 * -L1, s3, alpha=-L2), sb, alpha=-LW) + SHOULDER[2]
    ebx = r * c1 + SHOULDER[0]
    eby = r * s1 + SHOULDER[1]
    sbsg, sbcg = sb * sg, sb * cg
    rot = torch.stack([  # Rz(psi) Ry(beta) Rx(gamma)
        cp * cb, torch.addcmul(cp * sbsg, sp, cg, value=-1), torch.addcmul(cp * sbcg, sp, sg),
        sp * cb, torch.addcmul(sp * sbsg, cp, cg), torch.addcmul(sp * sbcg, cp, sg, value=-1),
        -sb, cb * sg, cb * cg,
    ], -1)
    return {
        "ee_b": torch.stack([ebx, eby, z], -1),
        "ee_x": torch.addcmul(torch.addcmul(bx, cy, ebx), sy, eby, value=-1),
        "ee_y": torch.addcmul(torch.addcmul(by, sy, ebx), cy, eby), "ee_z": z + STANDING_HEIGHT,
        "ee_rot": rot.unflatten(-1, (3, 3)), "cy": cy, "sy": sy,
        # Gripper yaw psi - q6 (exact for a downward gripper).
        "cg": torch.addcmul(cp * cg, sp, sg), "sg": torch.addcmul(sp * cg, cp, sg, value=-1),
    }


def wrist_in_reach(wx, wy, wzc):
    """A wrist centre relative to the shoulder scaled onto the reachable shell
    [REACH_MIN, REACH_MAX]; returns it and its horizontal distance squared."""
    dr2 = torch.addcmul(wx * wx, wy, wy)
    n2 = torch.addcmul(dr2, wzc, wzc)
    f2 = n2.clamp(REACH_MIN**2, REACH_MAX**2) / n2.clamp(min=1e-12)
    f = torch.sqrt(f2)
    return wx * f, wy * f, wzc * f, dr2 * f2


def ik_wrist(wx, wy, wzc, dr2, yaw_t, zero):
    """Joint targets [N, R, 6] for a wrist centre (wx, wy, wzc) relative to the shoulder
    (dr2 = wx^2 + wy^2, within reach) and gripper yaw ``yaw_t`` (base frame), as arm_ik."""
    c3 = ((torch.addcmul(dr2, wzc, wzc) - (L1 * L1 + L2 * L2)) * (1.0 / (2 * L1 * L2))).clamp(-1.0, 1.0)
    q3 = -torch.acos(c3)
    q2 = torch.atan2(-wzc, torch.sqrt(dr2)) - torch.atan2(L2 * torch.sin(q3), L2 * c3 + L1)
    q1 = torch.atan2(wy, wx)
    return torch.stack([q1, q2, q3, zero, (math.pi / 2 - q2) - q3, q1 - yaw_t], -1)

