"""Arm kinematics against MuJoCo, and IK accuracy."""
import mujoco
import numpy as np
import pytest
import torch

from pnp.sim.box import SINGLE_ROBOT_BOXES
from pnp.sim.arm_ik import ArmKinematics, gripper_yaw
from pnp.sim.robot import STANDING_HEIGHT
from pnp.sim.scene import build_scene


@pytest.fixture(scope="module")
def kin():
    return ArmKinematics(dtype=torch.float64)


@pytest.fixture(scope="module")
def scene():
    return build_scene(1, SINGLE_ROBOT_BOXES[0])


def test_fk_and_jacobian_match_mujoco(kin, scene):
    _, m, idx = scene
    d = mujoco.MjData(m)
    sid = m.site("robot0/ee_site").id
    g = torch.Generator().manual_seed(0)
    q = torch.rand(20, 6, generator=g, dtype=torch.float64) * (kin.q_high - kin.q_low) + kin.q_low
    pos, rot, jac = kin.fk_jacobian(q)
    for i in range(len(q)):
        d.qpos[idx.arm_qpos[0]] = q[i].numpy()
        d.qpos[idx.base_qpos[0]] = (0.3, -0.2, 0.0)  # base yaw 0: base frame = world axes
        mujoco.mj_forward(m, d)
        base = d.body("robot0/base").xpos
        jp, jr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
        mujoco.mj_jacSite(m, d, jp, jr, sid)
        cols = idx.arm_qvel[0]
        np.testing.assert_allclose(pos[i].numpy(), d.site_xpos[sid] - base, atol=1e-4)
        np.testing.assert_allclose(rot[i].numpy(), d.site_xmat[sid].reshape(3, 3), atol=1e-4)
        np.testing.assert_allclose(jac[i, :3].numpy(), jp[:, cols], atol=1e-4)
        np.testing.assert_allclose(jac[i, 3:].numpy(), jr[:, cols], atol=1e-4)


def test_our_fk_matches_pytorch_kinematics(kin):
    q = torch.linspace(-0.5, 0.5, 6, dtype=torch.float64).expand(3, 6) * torch.tensor([[1.0], [0.5], [-1.0]], dtype=torch.float64)
    q = q.clamp(kin.q_low, kin.q_high)
    ours = kin.fk(q)[0]
    m = kin.chain.forward_kinematics(q).get_matrix()
    # pk's chain is rooted at the standalone model's trunk, placed at the standing height.
    root = torch.tensor([0.0, 0.0, STANDING_HEIGHT], dtype=torch.float64)
    np.testing.assert_allclose(ours.numpy(), (m[:, :3, 3] - root).numpy(), atol=1e-6)
    np.testing.assert_allclose(kin.jacobian(q).numpy(), kin.chain.jacobian(q).numpy(), atol=1e-6)


def test_ik_reaches_reachable_targets(kin):
    g = torch.Generator().manual_seed(1)
    n = 256
    pos = torch.tensor([0.75, 0.0, -0.3], dtype=torch.float64) + (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * torch.tensor([0.4, 0.6, 0.3], dtype=torch.float64)
    yaw = (torch.rand(n, generator=g, dtype=torch.float64) - 0.5) * 2.0
    q = kin.ik(kin.q_default.expand(n, 6), pos, yaw, iters=8)
    p, r = kin.fk(q)
    err = (p - pos).norm(dim=-1)
    assert torch.quantile(err, 0.95) < 1e-3, err.max()
    assert (gripper_yaw(r) - yaw).abs().max() < 1e-2
