"""The arm's gravity feed-forward acts at the arm joints only: it holds the arm, never the trunk.

MuJoCo's body ``gravcomp`` on a floating-base robot also put the arm's weight on the free joint
(~90 N up and a pitch moment at rest, MuJoCo 3.17): these tests measure the force where it
must not act (the free joint, the falling robot's centre of mass) and where it must (the arm)."""
import mujoco
import numpy as np
import pytest

from pnp.legs.arm_gravity import ArmGravity
from pnp.sim.box import SINGLE_ROBOT_BOXES
from pnp.sim.robot import ARM_COMPENSATED, ARM_DEFAULT, ARM_JOINTS, Quadruped
from pnp.sim.scene import PnPArena, build_scene

G = 9.81


def _legged(gravcomp: bool = False) -> mujoco.MjModel:
    arena = PnPArena()
    robot = Quadruped(name="robot0", legs="actuated")
    robot.create_root_joints(arena.attach(robot))
    if gravcomp:  # the planar robot's MuJoCo gravcomp on the same bodies: the reference torques
        for b in ARM_COMPENSATED:
            robot.mjcf_model.find("body", b).gravcomp = 1
    root = arena.mjcf_model
    return mujoco.MjModel.from_xml_string(root.to_xml_string(), assets=root.get_assets())


def _arm(model, kind="joint"):
    return np.array([getattr(model, kind)(f"robot0/{n}").id for n in ARM_JOINTS])


def _hold(model, data):
    """Arm servos at the default pose, plus the feed-forward where the model has its motors."""
    data.ctrl[_arm(model, "actuator")] = ARM_DEFAULT
    if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, "robot0/arm_j1_ff") >= 0:
        ff = [model.actuator(f"robot0/{n}_ff").id for n in ARM_JOINTS]
        data.ctrl[ff] = ArmGravity(model, "robot0/", 0, ARM_COMPENSATED, ARM_JOINTS).torques(data.qpos[None])[0]


@pytest.fixture(scope="module")
def legged():
    return _legged()


def test_free_joint_receives_no_applied_force_at_rest(legged):
    m, d = legged, mujoco.MjData(legged)
    d.qpos[m.jnt_qposadr[_arm(m)]] = ARM_DEFAULT
    _hold(m, d)
    mujoco.mj_forward(m, d)
    applied = d.qfrc_passive[:6] + d.qfrc_actuator[:6] + d.qfrc_applied[:6]
    np.testing.assert_allclose(applied, 0.0, atol=1e-9)  # was [0, 0, 90.25, 0, -58.26, 0]


def test_robot_lifted_off_the_floor_falls_at_g(legged):
    m, d = legged, mujoco.MjData(legged)
    d.qpos[2] += 1.0
    d.qpos[m.jnt_qposadr[_arm(m)]] = ARM_DEFAULT
    steps = round(0.1 / m.opt.timestep)
    for _ in range(steps):
        _hold(m, d)
        mujoco.mj_step(m, d)
    base = m.body("robot0/base").id
    mujoco.mj_forward(m, d)  # mj_step leaves the velocity-derived quantities of the step's start
    mujoco.mj_subtreeVel(m, d)
    # Internal forces (servos, feed-forward) cannot change the whole robot's momentum.
    fall = d.subtree_linvel[base][2] / (steps * m.opt.timestep)
    assert fall == pytest.approx(-G, rel=1e-3)  # the lifted robot fell at -8.33 m/s^2


def test_feed_forward_equals_mujoco_gravcomp_on_the_arm_joints():
    m_ref, m = _legged(gravcomp=True), _legged()
    gravity = ArmGravity(m, "robot0/", 0, ARM_COMPENSATED, ARM_JOINTS)
    rng = np.random.default_rng(0)
    d = mujoco.MjData(m_ref)
    qpos = np.tile(m_ref.qpos0, (6, 1))
    for q in qpos:  # any trunk orientation, any arm and finger angle in range
        q[3:7] = rng.normal(size=4) / 1.0
        q[3:7] /= np.linalg.norm(q[3:7])
        for j in range(m_ref.njnt):
            if m_ref.jnt_type[j] in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
                q[m_ref.jnt_qposadr[j]] = rng.uniform(*m_ref.jnt_range[j])
    expected = []
    for q in qpos:
        d.qpos[:] = q
        mujoco.mj_forward(m_ref, d)
        expected.append(d.qfrc_gravcomp[m_ref.jnt_dofadr[_arm(m_ref)]].copy())
    np.testing.assert_allclose(gravity.torques(qpos), np.array(expected), atol=1e-9)
    assert np.abs(np.array(expected)).max() > 5.0  # the comparison is not of zeros


def test_arm_holds_its_pose_on_the_standing_robot(legged):
    m, d = legged, mujoco.MjData(legged)
    arm_q = m.jnt_qposadr[_arm(m)]
    d.qpos[arm_q] = ARM_DEFAULT
    for step in range(round(1.0 / m.opt.timestep)):
        if step % 4 == 0:  # updated once per low-level tick, as the envs do
            _hold(m, d)
        mujoco.mj_step(m, d)
    # Without the feed-forward the shoulder's 40 N m servo sags by ~0.06 rad.
    assert np.abs(d.qpos[arm_q] - ARM_DEFAULT).max() < 0.01


def test_planar_robot_keeps_gravcomp_and_its_base_joints_take_none():
    _, m, _ = build_scene(1, SINGLE_ROBOT_BOXES[0])
    d = mujoco.MjData(m)
    d.qpos[m.jnt_qposadr[_arm(m)]] = ARM_DEFAULT
    mujoco.mj_forward(m, d)
    base = [m.jnt_dofadr[m.joint(f"robot0/{n}").id] for n in ("base_x", "base_y", "base_yaw")]
    assert np.abs(d.qfrc_gravcomp[m.jnt_dofadr[_arm(m)]]).max() > 5.0  # it holds the arm
    np.testing.assert_allclose(d.qfrc_gravcomp[base], 0.0, atol=1e-9)  # a vertical force moves no planar joint
