"""The arm controller's gravity feed-forward on a floating-base robot, from the arm's own chain.

MuJoCo's body ``gravcomp`` maps each compensated body's upward force through the Jacobian
of *every* ancestor degree of freedom, the free joint included: on ``legs="actuated"`` it held
up ~90 N of the arm's weight and a pitch moment at the trunk for free (measured at rest:
``qfrc_actuator[:6] = [0, 0, 90.25, 0, -58.26, 0]``), whatever joint flag routes it. A real
arm controller only applies torques at its own joints; their reactions act on the trunk and
the legs must carry the arm. So the actuated robot has no ``gravcomp``; instead one motor per
arm joint (``arm_jK_ff``) receives the torque computed here from the arm's kinematic chain,
held for a low-level tick (the rigid robot keeps MuJoCo's gravcomp: its planar base joints
take none of a vertical force).

The torque at joint k holds the compensated bodies below it against gravity:
``tau_k = a_k . sum_j (c_j - p_k) x (m_j |g| e_up)``, with ``a_k``, ``p_k`` the joint's axis and
anchor and ``c_j``, ``m_j`` a body's centre of mass and mass, computed in the trunk frame from
the arm and finger joint angles and the trunk's orientation. Since every force points the same
way, the sum is ``tau_k = |g| a_k . ((S_k - M_k p_k) x up)`` with ``S_k`` the mass-weighted sum of
the centres below joint k and ``M_k`` their mass. Batched torch, float64: it runs once per
low-level tick in the env step.
"""
from __future__ import annotations

import mujoco
import numpy as np
import torch

from pnp.sim.backend import quat_to_matrix


def _skew(a: torch.Tensor) -> torch.Tensor:
    x, y, z = a.tolist()
    return torch.tensor([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]], dtype=torch.float64)


class ArmGravity:
    """Feed-forward torques for the arm joints of robot ``prefix`` (``"robot0/"``) in ``model``.

    ``bodies`` are the compensated bodies (the rigid robot's ``gravcomp`` set); every body of
    the arm's subtree takes part in the kinematics. ``torques(qpos)``: qpos [M, nq] -> [M, 6]."""

    def __init__(self, model: mujoco.MjModel, prefix: str, base_qpos: int, bodies: tuple[str, ...],
                 joints: tuple[str, ...]):
        root = model.body(f"{prefix}{bodies[0]}").id
        chain = [b for b in range(model.nbody) if self._descends(model, b, root)]
        names = {f"{prefix}{n}" for n in bodies}
        if not names <= {model.body(b).name for b in chain}:
            raise ValueError(f"compensated bodies {sorted(names)} are not all in the arm's subtree")
        f64 = dict(dtype=torch.float64)
        self._parent = [chain.index(model.body_parentid[b]) if b != root else -1 for b in chain]
        self._pos = torch.tensor(model.body_pos[chain], **f64)
        self._rot = quat_to_matrix(torch.tensor(model.body_quat[chain], **f64))
        self._ipos = torch.tensor(model.body_ipos[chain], **f64)
        mass = torch.tensor([model.body_mass[b] if model.body(b).name in names else 0.0 for b in chain], **f64)
        self._joint = []  # per body: (qposadr, "hinge" (K, K^2, anchor) | "slide" axis) or None
        for b in chain:
            jn = model.body_jntnum[b]
            if jn > 1:
                raise ValueError(f"body {model.body(b).name!r} has {jn} joints; the chain expects at most one")
            if jn == 0:
                self._joint.append(None)
                continue
            j = model.body_jntadr[b]
            axis, adr = torch.tensor(model.jnt_axis[j], **f64), int(model.jnt_qposadr[j])
            if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE:
                K = _skew(axis)
                self._joint.append((adr, "hinge", (K, K @ K, torch.tensor(model.jnt_pos[j], **f64))))
            elif model.jnt_type[j] == mujoco.mjtJoint.mjJNT_SLIDE:
                self._joint.append((adr, "slide", axis))
            else:
                raise ValueError(f"joint type {model.jnt_type[j]} in the arm chain: only hinges and slides are supported")
        self._arm = [chain.index(model.jnt_bodyid[model.joint(f"{prefix}{n}").id]) for n in joints]
        # Per arm joint: which bodies hang below it (as weights), their mass, its axis and anchor.
        below = torch.tensor([[float(self._in_subtree(j, k)) for j in range(len(chain))] for k in self._arm], **f64)
        self._weights = below * mass  # [J, B]: S_k = weights @ centres
        self._subtree_mass = self._weights.sum(1)  # [J]
        self._axes = torch.stack([torch.tensor(model.jnt_axis[model.body_jntadr[chain[k]]], **f64) for k in self._arm])
        self._anchors = torch.stack([self._joint[k][2][2] for k in self._arm])
        self._base_qpos = base_qpos
        self._g = float(np.linalg.norm(model.opt.gravity))

    @staticmethod
    def _descends(model, body: int, root: int) -> bool:
        while body > 0:
            if body == root:
                return True
            body = model.body_parentid[body]
        return False

    def _in_subtree(self, j: int, k: int) -> bool:
        while j >= 0:
            if j == k:
                return True
            j = self._parent[j]
        return False

    @torch.no_grad()
    def torques(self, qpos: np.ndarray) -> np.ndarray:
        """Joint torques [M, 6] holding the compensated bodies, for worlds' ``qpos`` [M, nq]."""
        q = torch.from_numpy(np.asarray(qpos, dtype=np.float64))
        M, eye = q.shape[0], torch.eye(3, dtype=torch.float64)
        up = quat_to_matrix(q[:, self._base_qpos + 3 : self._base_qpos + 7])[:, 2, :]  # world z in the trunk frame
        rots, origins, centres = [], [], []
        for k, parent in enumerate(self._parent):
            R_p = eye.expand(M, 3, 3) if parent < 0 else rots[parent]
            p = (self._pos[k] if parent < 0 else origins[parent] + R_p @ self._pos[k]).expand(M, 3)
            R = R_p @ self._rot[k]
            joint = self._joint[k]
            if joint is not None:
                adr, kind, data = joint
                angle = q[:, adr, None, None]
                if kind == "hinge":
                    K, K2, anchor = data
                    R_j = R @ (eye + torch.sin(angle) * K + (1 - torch.cos(angle)) * K2)  # Rodrigues
                    p = p + (R - R_j) @ anchor  # rotation about the anchor, not the body origin
                    R = R_j
                else:
                    p = p + (R @ data) * q[:, adr, None]
            rots.append(R)
            origins.append(p)
            centres.append(p + R @ self._ipos[k])
        centres = torch.stack(centres, 1)  # [M, B, 3]
        weighted = torch.einsum("jb,mbi->mji", self._weights, centres)  # S_k [M, J, 3]
        R_k = torch.stack([rots[k] for k in self._arm], 1)  # [M, J, 3, 3]
        p_k = torch.stack([origins[k] for k in self._arm], 1) + (R_k @ self._anchors.unsqueeze(-1))[..., 0]
        axes = R_k @ self._axes.unsqueeze(-1)  # [M, J, 3, 1]
        lever = weighted - self._subtree_mass[:, None] * p_k
        moment = torch.linalg.cross(lever, up[:, None, :].expand_as(lever))
        return (self._g * (moment * axes[..., 0]).sum(-1)).numpy()
