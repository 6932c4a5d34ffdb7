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
the arm and finger joint angles and the trunk's orientation. Batched, numpy, float64.
"""
from __future__ import annotations

import mujoco
import numpy as np


def _quat_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices [..., 3, 3] of unit quaternions [..., 4] (w, x, y, z)."""
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def _axis_rotation(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotations [..., 3, 3] by ``angle`` [...] about the unit ``axis`` [3]."""
    half = angle[..., None] / 2
    return _quat_matrix(np.concatenate([np.cos(half), np.sin(half) * axis], -1))


class ArmGravity:
    """Feed-forward torques for the arm joints of robot ``prefix`` (``"robot0/"``) in ``model``.

    ``bodies`` are the compensated bodies (the rigid robot's ``gravcomp`` set); every body of
    the arm's subtree takes part in the kinematics. ``torques(qpos)`` maps qpos [M, nq] (or
    [M, R, ...] via ``qpos`` per robot) to [M, 6]."""

    def __init__(self, model: mujoco.MjModel, prefix: str, base_qpos: int, bodies: tuple[str, ...],
                 joints: tuple[str, ...]):
        root = model.body(f"{prefix}{bodies[0]}").id
        chain = [b for b in range(model.nbody) if self._descends(model, b, root)]
        self._bodies = chain
        self._parent = [chain.index(model.body_parentid[b]) if b != root else -1 for b in chain]
        self._pos = model.body_pos[chain].copy()
        self._rot = _quat_matrix(model.body_quat[chain].copy())
        self._ipos = model.body_ipos[chain].copy()
        names = {f"{prefix}{n}" for n in bodies}
        self._mass = np.array([model.body_mass[b] if model.body(b).name in names else 0.0 for b in chain])
        if not names <= {model.body(b).name for b in chain}:
            raise ValueError(f"compensated bodies {sorted(names)} are not all in the arm's subtree")
        self._joint = []  # per body: (qposadr, type, axis, anchor) or None
        for b in chain:
            jn = model.body_jntnum[b]
            if jn > 1:
                raise ValueError(f"body {model.body(b).name!r} has {jn} joints; the chain expects at most one")
            if jn == 0:
                self._joint.append(None)
                continue
            j = model.body_jntadr[b]
            self._joint.append((int(model.jnt_qposadr[j]), int(model.jnt_type[j]), model.jnt_axis[j].copy(),
                                model.jnt_pos[j].copy()))
        self._arm = [chain.index(model.jnt_bodyid[model.joint(f"{prefix}{n}").id]) for n in joints]
        self._below = [[j for j in range(len(chain)) if self._in_subtree(j, k)] for k in self._arm]
        self._base_qpos = base_qpos
        self._g = float(np.linalg.norm(model.opt.gravity))

    @staticmethod
    def _descends(model, body: int, root: int) -> bool:
        while body > 0:
            if body == root:
                return True
            body = model.body_parentid[body]
        return False

    def torques(self, qpos: np.ndarray) -> np.ndarray:
        """Joint torques [M, 6] holding the compensated bodies, for worlds' ``qpos`` [M, nq]."""
        M = qpos.shape[0]
        up = _quat_matrix(qpos[:, self._base_qpos + 3 : self._base_qpos + 7]).swapaxes(-1, -2)[..., 2]  # world z in trunk
        rots, origins, coms = [], [], []
        for k, parent in enumerate(self._parent):
            R_p = np.broadcast_to(np.eye(3), (M, 3, 3)) if parent < 0 else rots[parent]
            p_p = np.zeros((M, 3)) if parent < 0 else origins[parent]
            R = R_p @ self._rot[k]
            p = p_p + R_p @ self._pos[k]
            joint = self._joint[k]
            if joint is not None:
                adr, typ, axis, anchor = joint
                if typ == mujoco.mjtJoint.mjJNT_HINGE:
                    R_j = R @ _axis_rotation(axis, qpos[:, adr])
                    p = p + (R - R_j) @ anchor  # rotation about the anchor, not the body origin
                    R = R_j
                elif typ == mujoco.mjtJoint.mjJNT_SLIDE:
                    p = p + (R @ axis) * qpos[:, adr, None]
                else:
                    raise ValueError(f"joint type {typ} in the arm chain: only hinges and slides are supported")
            rots.append(R)
            origins.append(p)
            coms.append(p + R @ self._ipos[k])
        coms = np.stack(coms, 1)  # [M, B, 3]
        lift = self._mass[None, :, None] * self._g * up[:, None, :]  # [M, B, 3] upward force per body
        out = np.empty((M, len(self._arm)))
        for i, (k, below) in enumerate(zip(self._arm, self._below)):
            _, _, axis, anchor = self._joint[k]
            p_k = origins[k] + rots[k] @ anchor
            moment = np.cross(coms[:, below] - p_k[:, None], lift[:, below]).sum(1)
            out[:, i] = np.einsum("mi,mi->m", moment, rots[k] @ axis)
        return out

    def _in_subtree(self, j: int, k: int) -> bool:
        while j >= 0:
            if j == k:
                return True
            j = self._parent[j]
        return False
