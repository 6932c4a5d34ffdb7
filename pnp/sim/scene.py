"""Arena and scene assembly: floor, goal marker, one or two robots and a box.

The scene is built once with dm_control composer Entities and compiled to a plain
``mujoco.MjModel``; batched stepping happens in ``pnp.sim.physics``.
"""
from __future__ import annotations

from dataclasses import dataclass

from pnp.sim import _offscreen  # noqa: F401  # sets MUJOCO_GL before mujoco loads

import mujoco
import numpy as np
from dm_control import composer, mjcf

from pnp.sim.box import BoxAsset, HandleBox
from pnp.sim.robot import ARM_JOINTS, Quadruped

PHYSICS_DT = 0.005  # s, 200 Hz (paper: physics at 200 Hz or faster)
GOAL_RADIUS = 0.5  # m, success radius (paper)


class PnPArena(composer.Entity):
    """Floor plane, lights and a goal marker (a mocap body, so each world can move it)."""

    def _build(self, name: str = "arena", physics_dt: float = PHYSICS_DT):
        self._mjcf_root = root = mjcf.RootElement(model=name)
        root.compiler.angle = "radian"
        root.option.timestep = physics_dt
        root.option.integrator = "implicitfast"
        root.option.cone = "elliptic"
        root.option.impratio = 5  # stiffer friction: handles must not slip out of the pads
        root.size.memory = "8M"
        # Box geoms are resized per world after compilation; the compiled per-body BVH
        # would then be stale, so skip midphase (bodies here have few geoms anyway).
        root.option.flag.midphase = "disable"
        root.visual.headlight.set_attributes(ambient=(0.4, 0.4, 0.4), diffuse=(0.6, 0.6, 0.6))
        root.visual.quality.shadowsize = 0
        root.asset.add("texture", name="grid", type="2d", builtin="checker", rgb1=(0.25, 0.3, 0.35), rgb2=(0.3, 0.35, 0.4), width=256, height=256)
        root.asset.add("material", name="grid", texture="grid", texrepeat=(8, 8))
        root.worldbody.add("geom", name="floor", type="plane", size=(20, 20, 0.1), material="grid", contype=1, conaffinity=1)
        goal = root.worldbody.add("body", name="goal", mocap=True, pos=(0, 0, 0))
        goal.add("geom", name="goal_disc", type="cylinder", size=(GOAL_RADIUS, 0.002), rgba=(0.1, 0.8, 0.2, 0.35), contype=0, conaffinity=0)
        root.worldbody.add("camera", name="overview", pos=(0, -6.5, 4.5), xyaxes=(1, 0, 0, 0, 0.6, 0.8))

    @property
    def mjcf_model(self):
        return self._mjcf_root


@dataclass
class SceneIndex:
    """Addresses into qpos/qvel/ctrl/sensordata of the compiled model."""

    base_qpos: np.ndarray  # [robots, 3] x, y, yaw
    base_qvel: np.ndarray  # [robots, 3]
    arm_qpos: np.ndarray  # [robots, 6]
    arm_qvel: np.ndarray  # [robots, 6]
    finger_qpos: np.ndarray  # [robots, 2]
    box_qpos: int  # start of the box free joint (pos 3, quat 4)
    box_qvel: int  # start of its velocity (lin 3, ang 3)
    base_ctrl: np.ndarray  # [robots, 3]
    arm_ctrl: np.ndarray  # [robots, 6]
    finger_ctrl: np.ndarray  # [robots, 2]
    touch: np.ndarray  # [robots, 2] sensordata addresses of the pad touch sensors
    box_body: int
    box_geoms: np.ndarray  # shell, handle bars, posts (resized per world)


def compose_scene(num_robots: int, box: BoxAsset, physics_dt: float = PHYSICS_DT, legs: str = "rigid"):
    """Arena, robots (``Quadruped(legs=...)``; actuated ones float) and box; returns ``(mjcf_root, mujoco.MjModel)``."""
    if num_robots not in (1, 2):
        raise ValueError(f"num_robots must be 1 or 2, got {num_robots!r}")
    arena = PnPArena(physics_dt=physics_dt)
    colours = ((0.85, 0.45, 0.1, 1), (0.85, 0.75, 0.2, 1))
    for i in range(num_robots):
        robot = Quadruped(name=f"robot{i}", rgba=colours[i], legs=legs)
        frame = arena.attach(robot)
        if legs == "actuated":
            robot.create_root_joints(frame)
    arena.attach(HandleBox(asset=box, name="box")).add("freejoint", name="box_free")
    root = arena.mjcf_model
    return root, mujoco.MjModel.from_xml_string(root.to_xml_string(), assets=root.get_assets())


def build_scene(num_robots: int, box: BoxAsset, physics_dt: float = PHYSICS_DT):
    """Compose the scene; returns ``(mjcf_root, mujoco.MjModel, SceneIndex)``."""
    root, model = compose_scene(num_robots, box, physics_dt)
    return root, model, index_scene(model, num_robots)


def index_scene(model: mujoco.MjModel, num_robots: int) -> SceneIndex:
    def jq(name):
        return model.jnt_qposadr[model.joint(name).id]

    def jv(name):
        return model.jnt_dofadr[model.joint(name).id]

    def act(name):
        return model.actuator(name).id

    R = range(num_robots)
    base = ("base_x", "base_y", "base_yaw")
    fingers = ("finger_l", "finger_r")
    free = [j for j in range(model.njnt) if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE][0]
    box_body = model.jnt_bodyid[free]
    geoms = [g for g in range(model.ngeom) if model.geom_bodyid[g] == box_body]
    return SceneIndex(
        base_qpos=np.array([[jq(f"robot{i}/{n}") for n in base] for i in R]),
        base_qvel=np.array([[jv(f"robot{i}/{n}") for n in base] for i in R]),
        arm_qpos=np.array([[jq(f"robot{i}/{n}") for n in ARM_JOINTS] for i in R]),
        arm_qvel=np.array([[jv(f"robot{i}/{n}") for n in ARM_JOINTS] for i in R]),
        finger_qpos=np.array([[jq(f"robot{i}/{n}") for n in fingers] for i in R]),
        box_qpos=int(model.jnt_qposadr[free]),
        box_qvel=int(model.jnt_dofadr[free]),
        base_ctrl=np.array([[act(f"robot{i}/{n}") for n in base] for i in R]),
        arm_ctrl=np.array([[act(f"robot{i}/{n}") for n in ARM_JOINTS] for i in R]),
        finger_ctrl=np.array([[act(f"robot{i}/{n}") for n in fingers] for i in R]),
        touch=np.array([[model.sensor_adr[model.sensor(f"robot{i}/pad_{s}_touch").id] for s in "lr"] for i in R]),
        box_body=int(box_body),
        box_geoms=np.array(geoms),
    )

