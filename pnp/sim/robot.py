"""An ANYmal D-like quadruped with a 6-DoF DynaArm-like arm and a 2F-140-like gripper.

Built from primitives with published numbers (see ``../shared/DESIGN.md``; sources:
ANYbotics ANYmal D and DynaArm data sheets, Robotiq 2F-140 manual). Numbers marked
"ours" are not published and were chosen for a plausible, stable model.

With the ideal low-level executor (``pnp.sim.executor``) the trunk rides on actuated
planar joints (x, y, yaw) at the standing height and the legs are rigid geometry,
shown in the standing pose; they collide with the box but not with the floor.

``legs="actuated"`` is the learned low level's robot: a free-floating trunk on 12 servoed
leg joints, each leg HAA (about x) -> HFE (about y) -> KFE (about y). Joints are built in
the standing pose with ``ref`` set to it, so the compiled ``qpos0`` is the stand while an
angle still reads 0 with the leg straight. Each servo is MuJoCo's ``<position>`` written
as a ``general`` actuator whose target is an offset from the stand: ``ctrl = 0`` holds
the stand, and a policy's action maps to ``ctrl = scale * action`` as in legged_gym
(``target = default + scale * action``). Only the feet touch the floor (as MuJoCo
Playground's Go1); trunk and leg links touch the box and the other robot's trunk and
legs, never each other within one robot (``<exclude>`` pairs). The arm is the same in
both variants.
"""
from __future__ import annotations

from pnp.sim import _offscreen  # noqa: F401  # sets MUJOCO_GL before dm_control loads

import itertools

import numpy as np
from dm_control import composer, mjcf

# --- ANYmal D (published) ---
TRUNK_MASS = 18.3  # kg
LEG_MASS = 8.3  # kg per leg (51.5 kg total without payload)
HAA_POS = (0.304, 0.109)  # m, hip abduction joints at (+-x, +-y, 0)
HFE_POS = (0.373, 0.115)  # m, hip flexion joints
THIGH_LEN = 0.285  # m
SHANK_LEN = 0.39  # m, knee to foot centre
FOOT_RADIUS = 0.0315  # m
HFE_STAND, KFE_STAND = 0.4, -0.8  # rad, standing pose (front legs; hind mirrored)
STANDING_HEIGHT = 0.59  # m, trunk centre above the floor
TRUNK_HALF = (0.30, 0.12, 0.09)  # ours: a box enclosing the published hip positions

# --- DynaArm (published lengths, torque and speed; masses split by us) ---
ARM_MOUNT = (0.25, 0.0, TRUNK_HALF[2])  # ours: on the front of the trunk's top plate
SHOULDER_HEIGHT = 0.09  # m (published 0.06-0.11)
UPPER_ARM = 0.41  # m
FOREARM = 0.41  # m (published 0.41-0.42)
WRIST = 0.12  # m
ARM_TORQUE = 40.0  # N m
ARM_SPEED = 4.0  # rad/s
ARM_LINK_MASSES = (2.0, 3.0, 1.0, 1.5, 1.0, 0.5)  # ours, ~9 kg + 1 kg gripper = ~10-11 kg
ARM_JOINTS = ("arm_j1", "arm_j2", "arm_j3", "arm_j4", "arm_j5", "arm_j6")
# Bodies the arm controller holds against gravity (not the fingers' 0.32 kg, as before legs).
ARM_COMPENSATED = ("arm_link1", "arm_link2", "arm_link3", "arm_link4", "arm_link5", "arm_link6", "gripper")
# Ours, narrower than the real arm's: the elbow stops short of straight, the shoulder of
# pointing up, and the forearm roll and wrist pitch exclude the flipped-wrist branch, so
# warm-started IK stays on one solution branch (yaw comes from j1 and j6).
ARM_RANGES = ((-2.8, 2.8), (-0.8, 2.6), (-2.8, -0.15), (-1.5, 1.5), (-0.5, 2.6), (-3.1, 3.1))
# Default arm pose (ours, solved by IK): gripper pointing down in front of the trunk.
ARM_DEFAULT = (0.0, 1.23, -1.71, 0.0, 2.05, 0.0)  # EE at (0.75, 0, -0.30) in the base frame

# --- Robotiq 2F-140 (published stroke and pads) ---
GRIPPER_MASS = 1.0  # kg
FINGER_STROKE = 0.07  # m per finger (140 mm total)
PAD_HALF = (0.015, 0.008, 0.035)  # pad 0.03 x 0.07 m; thickness ours
GRIPPER_LEN = 0.16  # ours: flange to the centre between the pads
FINGER_FORCE = 125.0  # N, published 2F-140 maximum grip force
FINGER_KP = 5000.0  # N/m, ours: ~75 N on a 30 mm bar

# Contact groups: floor 1, robot 2, box 4 (box collides with both; robot not with floor).
ROBOT_CONTYPE, ROBOT_CONAFFINITY = 2, 4

# --- Actuated legs (legs="actuated") ---
LEG_VARIANTS = ("rigid", "actuated")
LEGS = ("LF", "RF", "LH", "RH")
LEG_JOINTS = tuple(f"{leg}_{j}" for leg in LEGS for j in ("HAA", "HFE", "KFE"))
LEG_TORQUE = 80.0  # N m, ANYmal D (published, DESIGN.md "Robot model")
# rad/s, ANYmal D (published). MuJoCo has no joint speed limit: the low level's env is to
# read this constant (observation scale, termination); the model does not enforce it.
LEG_SPEED = 8.5
LEG_KP = 80.0  # N m/rad, legged_gym's ANYmal C (DESIGN.md "A learned low level")
LEG_KD = 2.0  # N m s/rad, same source
def leg_servo_params(kp, kd, q0) -> dict:
    """A leg actuator's gain and bias at stand angle ``q0``: force = kp (ctrl + q0 - q) - kd qdot."""
    return {"gainprm": (kp,), "biasprm": (kp * q0, -kp, -kd)}


LEG_ARMATURE = 0.02  # kg m^2, ours: reflected drive inertia
# Ranges of the left front leg (rad); right legs mirror HAA, hind legs HFE and KFE.
HAA_RANGE = (-0.785, 0.611)  # published; mirrored for the right legs (ours)
HFE_RANGE = (-1.2, 1.6)  # ours
KFE_RANGE = (-2.6, 0.0)  # ours: folded to straight, no over-extension
# Ours: the knee (and shank, foot) 0.10 m outboard of the HFE, as the thigh offset in
# ANYbotics' public ANYmal C description (KFE at y 0.1003 m in the thigh frame; the D
# data sheet gives no number). With the feet under the hips (0.23 m apart) the kp 80
# stand held only by symmetry: a 0.2 m/s sideways push toppled it up to kp 150 (measured).
KNEE_OUT = 0.10
HIP_MASS, THIGH_MASS, SHANK_MASS, FOOT_MASS = 2.5, 4.0, 1.6, 0.2  # ours: LEG_MASS split over the links
# Base height in the stand with the feet on the floor: 0.653 m, above the published 0.59 m
# because our links are straight segments of the published lengths; the kp 80 servos sag
# to about 0.633 m under the 61 kg robot (measured, tests/pnp/test_robot_legs.py).
LEGGED_STAND_HEIGHT = float(THIGH_LEN * np.cos(HFE_STAND) + SHANK_LEN * np.cos(HFE_STAND + KFE_STAND) + FOOT_RADIUS)
# Bit 8 marks the legged body: trunk and leg links touch the box (its conaffinity has 2)
# and the other robot's body (8), feet also the floor (1); not the arm (2, 4), as before.
LEG_CONTYPE, LEG_CONAFFINITY = 2 | 8, 4 | 8
FOOT_CONAFFINITY = LEG_CONAFFINITY | 1


def _leg_signs(leg: str) -> tuple[int, int]:
    """(+1 front / -1 hind, +1 left / -1 right)."""
    return (1 if leg[1] == "F" else -1), (1 if leg[0] == "L" else -1)


def stand_pose() -> np.ndarray:
    """Standing joint angles in ``LEG_JOINTS`` order: front knees point back, hind knees
    forward (ANYmal's X configuration, as the rigid legs)."""
    return np.array([q for leg in LEGS for q in (0.0, _leg_signs(leg)[0] * HFE_STAND, _leg_signs(leg)[0] * KFE_STAND)])


def leg_ranges() -> np.ndarray:
    """``[12, 2]`` joint ranges in ``LEG_JOINTS`` order."""
    signs = [s for leg in LEGS for s in (_leg_signs(leg)[1], _leg_signs(leg)[0], _leg_signs(leg)[0])]
    base = [HAA_RANGE, HFE_RANGE, KFE_RANGE] * len(LEGS)
    return np.array([sorted((s * lo, s * hi)) for s, (lo, hi) in zip(signs, base)])


class Quadruped(composer.Entity):
    """One-armed quadruped; ``name`` prefixes every element (``robot0/arm_j1``).

    ``legs="rigid"`` (default): planar base joints, rigid legs. ``legs="actuated"``: 12
    leg servos; attach it with ``robot.create_root_joints(parent.attach(robot))``."""

    def _build(self, name: str = "robot", rgba=(0.85, 0.45, 0.1, 1), legs: str = "rigid"):
        if legs not in LEG_VARIANTS:
            raise ValueError(f"legs must be one of {LEG_VARIANTS}, got {legs!r}")
        self._mjcf_root = root = mjcf.RootElement(model=name)
        root.default.geom.set_attributes(
            contype=ROBOT_CONTYPE, conaffinity=ROBOT_CONAFFINITY, rgba=rgba, friction=(1.0, 0.005, 0.0001)
        )
        self.legs = legs
        rigid = legs == "rigid"
        # Actuated: the free joint goes on the attachment frame (create_root_joints).
        base = root.worldbody.add("body", name="base", pos=(0, 0, STANDING_HEIGHT if rigid else 0.0))
        if rigid:
            # Ideal executor: planar joints, velocity-actuated (see pnp.sim.executor).
            for jn, typ, axis in (("base_x", "slide", (1, 0, 0)), ("base_y", "slide", (0, 1, 0)), ("base_yaw", "hinge", (0, 0, 1))):
                base.add("joint", name=jn, type=typ, axis=axis, damping=0.0, armature=1.0)
        trunk = base.add("geom", name="trunk", type="box", size=TRUNK_HALF, mass=TRUNK_MASS)
        base.add("site", name="base_site", size=(0.01,), rgba=(0, 0, 0, 0))
        if rigid:
            self._add_legs(base)
        else:
            trunk.set_attributes(contype=LEG_CONTYPE, conaffinity=LEG_CONAFFINITY)
            self._add_actuated_legs(root, base)
        self._add_arm(base)
        if rigid:  # the arm controller's feed-forward; on a free joint MuJoCo would lift the trunk too
            for name in ARM_COMPENSATED:
                root.find("body", name).gravcomp = 1
        if rigid:
            for jn in ("base_x", "base_y"):
                root.actuator.add("velocity", name=jn, joint=jn, kv=3000.0, forcerange=(-3000, 3000), forcelimited=True)
            root.actuator.add("velocity", name="base_yaw", joint="base_yaw", kv=800.0, forcerange=(-800, 800), forcelimited=True)
        for jn, (lo, hi) in zip(ARM_JOINTS, ARM_RANGES):
            root.actuator.add(
                "position", name=jn, joint=jn, kp=600.0, kv=40.0, ctrlrange=(lo, hi), ctrllimited=True,
                forcerange=(-ARM_TORQUE, ARM_TORQUE), forcelimited=True,
            )
        if not rigid:  # the arm controller's gravity feed-forward (pnp.legs.arm_gravity), unlimited as gravcomp
            for jn in ARM_JOINTS:
                root.actuator.add("motor", name=f"{jn}_ff", joint=jn, gear=(1,))
        for fn in ("finger_l", "finger_r"):
            root.actuator.add(
                "position", name=fn, joint=fn, kp=FINGER_KP, kv=30.0, ctrlrange=(0, FINGER_STROKE), ctrllimited=True,
                forcerange=(-FINGER_FORCE, FINGER_FORCE), forcelimited=True,
            )
        for side in ("l", "r"):
            root.sensor.add("touch", name=f"pad_{side}_touch", site=f"pad_{side}_site")

    def create_root_joints(self, attachment_frame):
        """Floating base of ``legs="actuated"``: ``frame = parent.attach(robot)`` then
        ``robot.create_root_joints(frame)``. MuJoCo allows free joints only in top-level
        bodies and the base sits under the attachment frame, so the free joint goes on the
        frame (composer's convention: ``Arena.add_free_entity``, the walkers). The base is
        at the frame's origin, so the joint's qpos is the trunk's pose; the frame starts
        at the stand height, so ``qpos0`` stands on the floor."""
        if self.legs != "actuated":
            raise ValueError("only legs='actuated' floats; the rigid robot rides its own planar joints")
        x, y, _ = attachment_frame.pos if attachment_frame.pos is not None else (0.0, 0.0, 0.0)
        attachment_frame.pos = (x, y, LEGGED_STAND_HEIGHT)
        attachment_frame.add("joint", name="base_free", type="free")

    def _add_legs(self, base):
        # Legs as rigid capsules in the standing pose: visual plus box collisions only.
        for sx, fore in ((1, "F"), (-1, "H")):
            for sy, side in ((1, "L"), (-1, "R")):
                hip = np.array([sx * HFE_POS[0], sy * HFE_POS[1], 0.0])
                # Front knees point back, hind knees forward (ANYmal's X configuration).
                hfe, kfe = sx * HFE_STAND, sx * KFE_STAND
                knee = hip + THIGH_LEN * np.array([-np.sin(hfe), 0, -np.cos(hfe)])
                foot = knee + SHANK_LEN * np.array([-np.sin(hfe + kfe), 0, -np.cos(hfe + kfe)])
                leg = f"{fore}{side}"
                m = LEG_MASS / 2
                base.add("geom", name=f"{leg}_thigh", type="capsule", fromto=(*hip, *knee), size=(0.045,), mass=m)
                base.add("geom", name=f"{leg}_shank", type="capsule", fromto=(*knee, *foot), size=(0.035,), mass=m)
                base.add("geom", name=f"{leg}_foot", type="sphere", pos=foot, size=(FOOT_RADIUS,), mass=0.1)

    def _add_actuated_legs(self, root, base):
        geom = dict(contype=LEG_CONTYPE, conaffinity=LEG_CONAFFINITY)
        joint = dict(type="hinge", limited=True, armature=LEG_ARMATURE)
        bodies = [base]
        poses, ranges = stand_pose().reshape(4, 3), leg_ranges().reshape(4, 3, 2)
        for leg, (haa, hfe, kfe), (r_haa, r_hfe, r_kfe) in zip(LEGS, poses, ranges):
            sx, sy = _leg_signs(leg)
            knee = (0, sy * KNEE_OUT, -THIGH_LEN)
            haa_pos = np.array([sx * HAA_POS[0], sy * HAA_POS[1], 0.0])
            hfe_pos = np.array([sx * HFE_POS[0], sy * HFE_POS[1], 0.0]) - haa_pos
            hip = base.add("body", name=f"{leg}_hip", pos=haa_pos)
            hip.add("joint", name=f"{leg}_HAA", axis=(1, 0, 0), range=r_haa, ref=haa, **joint)
            hip.add("geom", name=f"{leg}_hip", type="capsule", fromto=(0, 0, 0, *hfe_pos), size=(0.05,), mass=HIP_MASS, **geom)
            # Bodies sit in the stand (rotated about y); ref makes that qpos0.
            thigh = hip.add("body", name=f"{leg}_thigh", pos=hfe_pos, quat=(np.cos(hfe / 2), 0, np.sin(hfe / 2), 0))
            thigh.add("joint", name=f"{leg}_HFE", axis=(0, 1, 0), range=r_hfe, ref=hfe, **joint)
            thigh.add("geom", name=f"{leg}_thigh", type="capsule", fromto=(0, 0, 0, *knee), size=(0.045,), mass=THIGH_MASS, **geom)
            shank = thigh.add("body", name=f"{leg}_shank", pos=knee, quat=(np.cos(kfe / 2), 0, np.sin(kfe / 2), 0))
            shank.add("joint", name=f"{leg}_KFE", axis=(0, 1, 0), range=r_kfe, ref=kfe, **joint)
            shank.add("geom", name=f"{leg}_shank", type="capsule", fromto=(0, 0, 0, 0, 0, -SHANK_LEN), size=(0.035,), mass=SHANK_MASS, **geom)
            shank.add(
                "geom", name=f"{leg}_foot", type="sphere", pos=(0, 0, -SHANK_LEN), size=(FOOT_RADIUS,), mass=FOOT_MASS,
                contype=LEG_CONTYPE, conaffinity=FOOT_CONAFFINITY,
            )
            bodies += [hip, thigh, shank]
        for jn, q0, (lo, hi) in zip(LEG_JOINTS, stand_pose(), leg_ranges()):
            # <position kp kv> with the target offset by the stand: force = kp (ctrl + q0 - q) - kd qdot.
            root.actuator.add(
                "general", name=jn, joint=jn, gaintype="fixed", biastype="affine",
                **leg_servo_params(LEG_KP, LEG_KD, q0), ctrlrange=(lo - q0, hi - q0),
                ctrllimited=True, forcerange=(-LEG_TORQUE, LEG_TORQUE), forcelimited=True,
            )
        for a, b in itertools.combinations(bodies, 2):
            if b.parent is not a:  # MuJoCo already drops parent-child pairs
                root.contact.add("exclude", body1=a, body2=b)

    def _add_arm(self, base):
        r = ARM_RANGES
        m = ARM_LINK_MASSES
        j = dict(type="hinge", armature=0.05, damping=1.0, limited=True)
        l1 = base.add("body", name="arm_link1", pos=ARM_MOUNT)
        l1.add("joint", name="arm_j1", axis=(0, 0, 1), range=r[0], **j)
        l1.add("geom", type="cylinder", fromto=(0, 0, 0, 0, 0, SHOULDER_HEIGHT), size=(0.055,), mass=m[0])
        l2 = l1.add("body", name="arm_link2", pos=(0, 0, SHOULDER_HEIGHT))
        l2.add("joint", name="arm_j2", axis=(0, 1, 0), range=r[1], **j)
        l2.add("geom", type="capsule", fromto=(0, 0, 0, UPPER_ARM, 0, 0), size=(0.045,), mass=m[1])
        l3 = l2.add("body", name="arm_link3", pos=(UPPER_ARM, 0, 0))
        l3.add("joint", name="arm_j3", axis=(0, 1, 0), range=r[2], **j)
        l3.add("geom", type="capsule", fromto=(0, 0, 0, 0.1, 0, 0), size=(0.04,), mass=m[2])
        l4 = l3.add("body", name="arm_link4", pos=(0.1, 0, 0))
        l4.add("joint", name="arm_j4", axis=(1, 0, 0), range=r[3], **j)
        l4.add("geom", type="capsule", fromto=(0, 0, 0, FOREARM - 0.1, 0, 0), size=(0.035,), mass=m[3])
        l5 = l4.add("body", name="arm_link5", pos=(FOREARM - 0.1, 0, 0))
        l5.add("joint", name="arm_j5", axis=(0, 1, 0), range=r[4], **j)
        l5.add("geom", type="capsule", fromto=(0, 0, 0, WRIST, 0, 0), size=(0.03,), mass=m[4])
        l6 = l5.add("body", name="arm_link6", pos=(WRIST, 0, 0))
        l6.add("joint", name="arm_j6", axis=(1, 0, 0), range=r[5], **j)
        self._add_gripper(l6)

    def _add_gripper(self, flange):
        # Gripper frame: x along the approach direction; fingers close along y.
        g = flange.add("body", name="gripper", pos=(0, 0, 0))
        g.add("geom", name="palm", type="box", pos=(0.04, 0, 0), size=(0.04, 0.075, 0.03), mass=GRIPPER_MASS * 0.7)
        g.add("site", name="ee_site", pos=(GRIPPER_LEN, 0, 0), size=(0.012,), rgba=(1, 0, 0, 0.6))
        fx = GRIPPER_LEN
        for side, sgn in (("l", 1), ("r", -1)):
            f = g.add("body", name=f"finger_{side}_body", pos=(fx, 0, 0))
            # q = 0 fully closed (pads touch at y = 0); q = stroke fully open.
            f.add("joint", name=f"finger_{side}", type="slide", axis=(0, sgn, 0), range=(0, FINGER_STROKE), armature=0.01, damping=2.0)
            f.add(
                "geom", name=f"pad_{side}", type="box", pos=(0, sgn * PAD_HALF[1], 0),
                size=(PAD_HALF[2], PAD_HALF[1], PAD_HALF[0]), mass=GRIPPER_MASS * 0.15,
                friction=(1.5, 0.01, 0.001), condim=4, rgba=(0.2, 0.2, 0.2, 1),
            )
            f.add("geom", type="box", pos=(-0.06, sgn * PAD_HALF[1], 0), size=(0.025, PAD_HALF[1], 0.012), mass=0.01)
            f.add("site", name=f"pad_{side}_site", type="box", pos=(0, sgn * PAD_HALF[1], 0),
                  size=(PAD_HALF[2] + 0.003, PAD_HALF[1] + 0.004, PAD_HALF[0] + 0.003), rgba=(0, 1, 0, 0.0))

    @property
    def mjcf_model(self):
        return self._mjcf_root
