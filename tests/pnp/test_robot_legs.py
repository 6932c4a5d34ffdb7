"""The floating-base robot with actuated legs (``Quadruped(legs="actuated")``) beside the default."""
import mujoco
import numpy as np
import pytest

from pnp.legs.arm_gravity import ArmGravity
from pnp.sim.box import SINGLE_ROBOT_BOXES, HandleBox
from pnp.legs.locomotion import LegServo
from pnp.sim.robot import (
    ARM_COMPENSATED, ARM_DEFAULT, ARM_JOINTS, LEG_JOINTS, LEG_KD, LEG_KP, LEG_MASS, LEG_SPEED, LEG_TORQUE,
    LEGGED_STAND_HEIGHT, STANDING_HEIGHT, TRUNK_MASS, Quadruped, leg_ranges, stand_pose,
)
from pnp.sim.scene import PnPArena, build_scene

RIGID_JOINTS = ["base_x", "base_y", "base_yaw", *ARM_JOINTS, "finger_l", "finger_r"]


def _legged_scene(num_robots: int = 1, box: bool = False) -> mujoco.MjModel:
    arena = PnPArena()
    for i in range(num_robots):
        robot = Quadruped(name=f"robot{i}", legs="actuated")
        robot.create_root_joints(arena.attach(robot))
    if box:
        arena.attach(HandleBox(asset=SINGLE_ROBOT_BOXES[0], name="box")).add("freejoint")
    root = arena.mjcf_model
    return mujoco.MjModel.from_xml_string(root.to_xml_string(), assets=root.get_assets())


def _ids(model, names, kind="joint"):
    return np.array([getattr(model, kind)(n).id for n in names])


def _robot_of(model, geom) -> str:
    name = model.geom(geom).name
    return name.split("/")[0]


@pytest.fixture(scope="module")
def legged():
    return _legged_scene()


def test_default_model_is_unchanged():
    robot = Quadruped(name="robot0")
    assert robot.mjcf_model.to_xml_string() == Quadruped(name="robot0", legs="rigid").mjcf_model.to_xml_string()
    _, model, _ = build_scene(1, SINGLE_ROBOT_BOXES[0])
    robot_joints = [model.joint(j).name for j in range(model.njnt) if model.joint(j).name.startswith("robot0/")]
    assert robot_joints == [f"robot0/{n}" for n in RIGID_JOINTS]
    assert [model.actuator(a).name for a in range(model.nu)] == [f"robot0/{n}" for n in RIGID_JOINTS]
    with pytest.raises(ValueError):
        Quadruped(name="robot0", legs="wheels")
    with pytest.raises(ValueError):
        robot.create_root_joints(None)


def test_actuated_model_floats_on_twelve_leg_servos(legged):
    m = legged
    free = [j for j in range(m.njnt) if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE]
    assert [m.joint(j).name for j in free] == ["robot0/base_free/"]
    assert all(f"robot0/{n}" not in [m.joint(j).name for j in range(m.njnt)] for n in ("base_x", "base_y", "base_yaw"))
    legs = _ids(m, [f"robot0/{n}" for n in LEG_JOINTS], "actuator")
    assert [m.actuator(a).name for a in range(m.nu)] == [f"robot0/{n}" for n in (*LEG_JOINTS, *ARM_JOINTS, *(f"{n}_ff" for n in ARM_JOINTS), "finger_l", "finger_r")]
    np.testing.assert_allclose(m.actuator_gainprm[legs, 0], LEG_KP)
    np.testing.assert_allclose(m.actuator_biasprm[legs, 1:3], np.tile([-LEG_KP, -LEG_KD], (12, 1)))
    np.testing.assert_allclose(m.actuator_forcerange[legs], np.tile([-LEG_TORQUE, LEG_TORQUE], (12, 1)))
    assert (LEG_TORQUE, LEG_SPEED, LEG_KP, LEG_KD) == (80.0, 8.5, 80.0, 2.0)  # published, anchor
    joints = _ids(m, [f"robot0/{n}" for n in LEG_JOINTS])
    np.testing.assert_allclose(m.jnt_range[joints], leg_ranges())
    np.testing.assert_allclose(m.jnt_range[m.joint("robot0/LF_HAA").id], (-0.785, 0.611))  # published
    # qpos0 is the stand, and ctrl = 0 targets it: the servos push nothing at qpos0.
    np.testing.assert_allclose(m.qpos0[m.jnt_qposadr[joints]], stand_pose())
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    np.testing.assert_allclose(d.actuator_force[legs], 0.0, atol=1e-9)
    assert d.qpos[2] == pytest.approx(LEGGED_STAND_HEIGHT)
    # No gravcomp in the model: the arm's feed-forward is its motors' (tests/pnp/test_arm_gravity.py).
    np.testing.assert_allclose(d.qfrc_gravcomp, 0.0, atol=1e-9)
    # Published trunk and legs (8.3 kg each, split over the links) plus the unchanged arm: 61 kg.
    leg_masses = [m.body_subtreemass[m.body(f"robot0/{leg}_hip").id] for leg in ("LF", "RF", "LH", "RH")]
    np.testing.assert_allclose(leg_masses, LEG_MASS)
    arm_mass = m.body_subtreemass[m.body("robot0/arm_link1").id]
    assert m.body_subtreemass[m.body("robot0/base").id] == pytest.approx(TRUNK_MASS + 4 * LEG_MASS + arm_mass)
    assert 60.0 < m.body_subtreemass[m.body("robot0/base").id] < 63.0


@pytest.mark.parametrize("kp, kd", [(LEG_KP, LEG_KD), (250.0, 6.0)])  # robot.py's; the trained legs'
def test_pd_hold_keeps_the_trunk_standing(kp, kd):
    m = _legged_scene()
    LegServo(kp=kp, kd=kd).apply(m, _ids(m, [f"robot0/{n}" for n in LEG_JOINTS], "actuator"))
    d = mujoco.MjData(m)
    arm_q = m.jnt_qposadr[_ids(m, [f"robot0/{n}" for n in ARM_JOINTS])]
    d.qpos[arm_q] = ARM_DEFAULT
    d.ctrl[_ids(m, [f"robot0/{n}" for n in ARM_JOINTS], "actuator")] = ARM_DEFAULT
    d.qpos[2] += 0.01  # dropped from 1 cm
    d.qvel[1] = 0.2  # and pushed sideways: a symmetric drop alone cannot show a lateral tip-over
    leg_dofs = m.jnt_dofadr[_ids(m, [f"robot0/{n}" for n in LEG_JOINTS])]
    heights, uprights, speed = [], [], 0.0
    gravity = ArmGravity(m, "robot0/", 0, ARM_COMPENSATED, ARM_JOINTS)
    ff = _ids(m, [f"robot0/{n}_ff" for n in ARM_JOINTS], "actuator")
    for step in range(round(2.0 / m.opt.timestep)):
        if step % 4 == 0:  # the arm's feed-forward, once per low-level tick as the envs do
            d.ctrl[ff] = gravity.torques(d.qpos[None])[0]
        mujoco.mj_step(m, d)
        speed = max(speed, np.abs(d.qvel[leg_dofs]).max())
        heights.append(d.qpos[2])
        uprights.append(1 - 2 * (d.qpos[4] ** 2 + d.qpos[5] ** 2))  # world z of the trunk's z axis
    # Measured with the arm's weight on the legs (no gravcomp lift): kp 80 sags to 0.600 m,
    # pitches 7.0 deg and creeps 0.17 m in 2 s (with the lift: 0.633 m, < 5 deg, < 5 cm);
    # kp 250 / kd 6 holds 0.645 m, 0.7 deg, 1.4 cm.
    soft = kp < 100
    assert abs(heights[-1] - STANDING_HEIGHT) < 0.06 and heights[-1] < LEGGED_STAND_HEIGHT
    assert min(heights) > STANDING_HEIGHT - (0.03 if soft else 0.0)
    assert min(uprights) > np.cos(np.radians(10 if soft else 2))
    assert speed < LEG_SPEED  # the model does not enforce it; a hold stays far below
    assert np.linalg.norm(d.qpos[:2]) < (0.25 if soft else 0.05) and abs(2 * np.arctan2(d.qpos[6], d.qpos[3])) < 0.15
    floor = m.geom("floor").id
    on_floor = {m.geom(c.geom1 + c.geom2 - floor).name for c in d.contact[: d.ncon] if floor in (c.geom1, c.geom2)}
    assert on_floor == {f"robot0/{leg}_foot" for leg in ("LF", "RF", "LH", "RH")}


def test_only_feet_touch_the_floor_and_links_touch_box_and_other_robot():
    m = _legged_scene(num_robots=2, box=True)
    d = mujoco.MjData(m)
    free = [m.jnt_qposadr[j] for j in range(m.njnt) if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE]
    r0, r1, box = free
    # Both robots sunk into the floor to mid-trunk (every leg link crosses it), overlapping
    # side by side; the box in robot0's front legs.
    d.qpos[r0 : r0 + 3] = (0.0, 0.0, 0.05)
    d.qpos[r1 : r1 + 3] = (0.0, 0.2, 0.05)
    d.qpos[box : box + 3] = (0.4, 0.0, 0.05)
    mujoco.mj_forward(m, d)
    pairs = {tuple(sorted((_robot_of(m, c.geom1), _robot_of(m, c.geom2)))) for c in d.contact[: d.ncon]}
    floor_hits = {m.geom(c.geom1 + c.geom2 - m.geom("floor").id).name for c in d.contact[: d.ncon] if m.geom("floor").id in (c.geom1, c.geom2)}
    assert floor_hits and all(n.endswith("_foot") or not n.startswith("robot") for n in floor_hits)
    assert ("robot0", "robot1") in pairs and ("box", "robot0") in pairs
    assert ("robot0", "robot0") not in pairs and ("robot1", "robot1") not in pairs
