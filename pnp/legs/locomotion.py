"""The learned low level's locomotion task (issue 24): one ``Quadruped(legs="actuated")`` per
world tracks a base-velocity command while its arm moves and carries a payload.

Anchored on legged_gym's ANYmal C flat task (DESIGN.md "A learned low level"): physics at
200 Hz, decimation 4 (policy at 50 Hz), joint targets ``stand + 0.5 * action``, commands
resampled every 4 s, its reward terms and scales. Ours: the arm's motion and payload, the
fall limits (only the feet touch the floor here, so a fallen trunk sinks instead of hitting
it), and a penalty beyond the published joint speed (the model does not enforce it).

The scene, the batched stepper (``mujoco.rollout`` on one shared model: nothing varies per
world but the payload, an external force), the state read-outs and the reward terms live
here; ``pnp.envs.locomotion_env`` wraps them as a TorchRL env. Shapes: N worlds, 4 feet,
12 leg joints.
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

from pnp.sim import _offscreen  # noqa: F401  # sets MUJOCO_GL before mujoco loads

import mujoco
import numpy as np
import torch
from mujoco import rollout

from pnp.sim.arm_closed_form import arm_ik
from pnp.legs.arm_gravity import ArmGravity
from pnp.sim.arm_ik import clamp_reach
from pnp.sim.robot import (
    ARM_COMPENSATED, ARM_JOINTS, ARM_RANGES, LEG_JOINTS, LEG_KD, LEG_KP, LEG_SPEED, LEG_TORQUE, LEGS, Quadruped, leg_ranges,
    leg_servo_params, stand_pose,
)
from pnp.sim.scene import PHYSICS_DT, PnPArena
from pnp.task.stage_graph import StageGraph
from pnp.task import ACTION_HIGH, ACTION_LOW
from pnp.sim.cores import available_cores

DECIMATION = 4  # physics steps per policy step (legged_gym)
POLICY_DT = DECIMATION * PHYSICS_DT  # 0.02 s, 50 Hz
ACTION_SCALE = 0.5  # rad: joint target = stand + 0.5 * action, action in [-1, 1] (legged_gym's scale)
EPISODE_S = 20.0  # legged_gym's episode length
TRACKING_SIGMA = 0.25  # (m/s)^2 and (rad/s)^2, legged_gym's tracking kernel exp(-err^2 / sigma)
AIR_TIME_TARGET = 0.5  # s, legged_gym's feet air time: steps longer than this pay
# EE targets of the moving arm: the HL action's EE box (pnp.task ACTION_LOW/HIGH: x, y, z, yaw).
EE_LOW, EE_HIGH = ACTION_LOW[3:7], ACTION_HIGH[3:7]

# (name, scale): legged_gym's ANYmal C flat scales, multiplied by POLICY_DT as legged_gym does
# (_prepare_reward_function), so a step's reward equals legged_gym's. legged_gym also clips the
# summed reward at 0 (only_positive_rewards); the reward schedule here cannot, so we do not.
# Its "collision" term (-1, thighs and shanks on the ground) has nothing to count: only the feet
# touch the floor. Ours: joint_speed (legged_gym's dof_vel_limits form, at the published
# 8.5 rad/s) and fall (legged_gym's termination scale is 0; ours -1 per fall, the reward of
# ~33 steps of perfect tracking, on top of the episode's lost rest).
REWARD_SCALES: tuple[tuple[str, float], ...] = (
    ("tracking_lin_vel", 1.0),
    ("tracking_ang_vel", 0.5),
    ("lin_vel_z", -2.0),
    ("ang_vel_xy", -0.05),
    ("orientation", -5.0),
    ("torques", -2.5e-5),
    ("dof_acc", -2.5e-7),
    ("action_rate", -0.01),
    ("feet_air_time", 2.0),
    ("joint_speed", -1.0),
    ("fall", -50.0),
)
LOCO_REWARD_TERMS = tuple(n for n, _ in REWARD_SCALES)
LOCO_REWARD_WEIGHTS = {n: s * POLICY_DT for n, s in REWARD_SCALES}
# Observation per robot: legged_gym's 48 entries plus the arm's joints (its weight moves).
LOCO_OBS_SIZES = {"base_lin_vel": 3, "base_ang_vel": 3, "projected_gravity": 3, "command": 3,
                  "leg_q": 12, "leg_qd": 12, "last_action": 12, "arm_q": 6}
_ENDS = list(itertools.accumulate(LOCO_OBS_SIZES.values()))
LOCO_OBS_FIELDS = {k: slice(e - n, e) for (k, n), e in zip(LOCO_OBS_SIZES.items(), _ENDS)}
LOCO_OBS_DIM = _ENDS[-1]  # 54
N_LEG = len(LEG_JOINTS)
STAND = torch.tensor(stand_pose(), dtype=torch.float32)
_LEG_LO, _LEG_HI = (torch.tensor(leg_ranges()[:, i], dtype=torch.float32) for i in (0, 1))
_ARM_LO, _ARM_HI = (torch.tensor([r[i] for r in ARM_RANGES]) for i in (0, 1))
_WEIGHTS = torch.tensor([[LOCO_REWARD_WEIGHTS[n]] for n in LOCO_REWARD_TERMS])

FULL = mujoco.mjtState.mjSTATE_FULLPHYSICS
CONTROL = mujoco.mjtState.mjSTATE_CTRL | mujoco.mjtState.mjSTATE_XFRC_APPLIED


def locomotion_stage_graph() -> StageGraph:
    """One stage, no condition: StageGraph allows it (S0 is also the last stage, never left),
    so the trainer's StageTransition runs unchanged and every stage one-hot is [1]."""
    return StageGraph(("walking",), ())


def locomotion_reward_config() -> dict:
    """Keyword arguments of ``pnp.transforms.make_reward_schedule``: every term fixed."""
    return dict(term_names=LOCO_REWARD_TERMS, term_stage={}, mu={}, fixed_weights=dict(LOCO_REWARD_WEIGHTS),
                low={}, high={}, n_stages=1)


def default_reward(terms: torch.Tensor) -> torch.Tensor:
    """[N, 1, T] -> [N, 1, 1] at the fixed weights (the env's own reward)."""
    return terms @ _WEIGHTS.to(terms.dtype)


# --- scene --------------------------------------------------------------------------------
class LocomotionIndex:
    """Addresses into qpos/qvel/ctrl/sensordata/xfrc of the compiled one-robot model."""

    def __init__(self, model: mujoco.MjModel):
        def jq(n):
            return int(model.jnt_qposadr[model.joint(f"robot0/{n}").id])

        def jv(n):
            return int(model.jnt_dofadr[model.joint(f"robot0/{n}").id])

        free = [j for j in range(model.njnt) if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE]
        if len(free) != 1:
            raise ValueError(f"expected one free joint (the trunk), found {len(free)}")
        self.base_qpos, self.base_qvel = int(model.jnt_qposadr[free[0]]), int(model.jnt_dofadr[free[0]])
        self.leg_qpos = np.array([jq(n) for n in LEG_JOINTS])
        self.leg_qvel = np.array([jv(n) for n in LEG_JOINTS])
        self.arm_qpos = np.array([jq(n) for n in ARM_JOINTS])
        self.finger_qpos = np.array([jq(n) for n in ("finger_l", "finger_r")])
        act = lambda names: np.array([model.actuator(f"robot0/{n}").id for n in names])  # noqa: E731
        self.leg_ctrl, self.arm_ctrl = act(LEG_JOINTS), act(ARM_JOINTS)
        self.arm_ff_ctrl = act([f"{n}_ff" for n in ARM_JOINTS])
        self.arm_gravity = ArmGravity(model, "robot0/", self.base_qpos, ARM_COMPENSATED, ARM_JOINTS)
        self.finger_ctrl = act(("finger_l", "finger_r"))
        self.gripper_body = int(model.body("robot0/gripper").id)
        self.foot_contact = np.array([model.sensor_adr[model.sensor(f"{leg}_foot_floor").id] for leg in LEGS])


def build_locomotion_scene(physics_dt: float = PHYSICS_DT) -> tuple[mujoco.MjModel, LocomotionIndex]:
    """The PnP arena (floor, same solver options) with one legged robot and a floor-contact
    sensor per foot (1 while touching; legged_gym thresholds the force at 1 N instead),
    composed in the arena: the robot's MJCF is not edited."""
    arena = PnPArena(physics_dt=physics_dt)
    robot = Quadruped(name="robot0", legs="actuated")
    robot.create_root_joints(arena.attach(robot))
    root = arena.mjcf_model
    floor = root.find("geom", "floor")
    for leg in LEGS:
        root.sensor.add("contact", name=f"{leg}_foot_floor", geom1=robot.mjcf_model.find("geom", f"{leg}_foot"),
                        geom2=floor, num=1, data="found")
    model = mujoco.MjModel.from_xml_string(root.to_xml_string(), assets=root.get_assets())
    return model, LocomotionIndex(model)


class LocomotionPhysics:
    """N worlds of one shared model stepped by ``mujoco.rollout`` on a persistent thread pool.

    External wrenches (``xfrc``, [N, nbody, 6], world frame) are held constant across steps:
    the payloads. Exposes ``get_state``/``set_state``/``close`` as the envs' backends do.
    """

    def __init__(self, model: mujoco.MjModel, num_worlds: int, nthread: int | None = None):
        self.model, self.num_worlds = model, num_worlds
        self.nthread = nthread or available_cores()
        self._models = [model] * num_worlds
        self._datas = [mujoco.MjData(model) for _ in range(self.nthread)]
        self._pool = rollout.Rollout(nthread=self.nthread)
        self.nstate = mujoco.mj_stateSize(model, FULL)
        self.state = np.zeros((num_worlds, self.nstate))
        mujoco.mj_getState(model, mujoco.MjData(model), self.state[0], FULL)
        self.state[:] = self.state[0]
        self.sensordata = np.zeros((num_worlds, model.nsensordata))
        self.xfrc = np.zeros((num_worlds, model.nbody, 6))
        self._out: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def qpos(self) -> np.ndarray:
        return self.state[:, 1 : 1 + self.model.nq]

    @property
    def qvel(self) -> np.ndarray:
        return self.state[:, 1 + self.model.nq : 1 + self.model.nq + self.model.nv]

    @property
    def time(self) -> np.ndarray:
        return self.state[:, 0]

    def reset_worlds(self, ids: np.ndarray, qpos: np.ndarray) -> None:
        """Worlds ``ids`` at rest in ``qpos``: zero velocity, time and actuator state."""
        fresh = np.zeros((len(ids), self.nstate))
        fresh[:, 1 : 1 + self.model.nq] = qpos
        self.state[ids] = fresh
        self.sensordata[ids] = 0.0

    def step(self, ctrl: np.ndarray, nsub: int) -> np.ndarray:
        """Advance every world ``nsub`` substeps holding ``ctrl`` [N, nu]; returns the worlds
        that diverged (NaN/Inf, or MuJoCo's own reset to time 0), left for the caller to reset."""
        n = self.num_worlds
        control = np.concatenate([ctrl, self.xfrc.reshape(n, -1)], -1)[:, None]
        control = np.ascontiguousarray(np.broadcast_to(control, (n, nsub, control.shape[-1])))
        if self._out is None or self._out[0].shape[1] != nsub:
            self._out = (np.empty((n, nsub, self.nstate)), np.empty((n, nsub, self.model.nsensordata)))
        state, sens = self._out
        t0 = self.time.copy()
        self._pool.rollout(self._models, self._datas, self.state, control, control_spec=CONTROL, skip_checks=True,
                           nstep=nsub, state=state, sensordata=sens)
        self.state, self.sensordata = state[:, -1].copy(), sens[:, -1].copy()
        expected = t0 + nsub * self.model.opt.timestep
        return ~np.isfinite(self.state).all(1) | (np.abs(self.time - expected) > 0.5 * self.model.opt.timestep)

    def get_state(self) -> dict[str, torch.Tensor]:
        return {k: torch.from_numpy(getattr(self, k).copy()) for k in ("state", "sensordata", "xfrc")}

    def set_state(self, state: dict[str, torch.Tensor]) -> None:
        for k in ("state", "sensordata", "xfrc"):
            setattr(self, k, state[k].numpy().copy())

    def close(self) -> None:
        self._pool.close()


# --- read-outs ----------------------------------------------------------------------------
def base_readouts(qpos: torch.Tensor, qvel: torch.Tensor, adr: int, dof: int) -> dict[str, torch.Tensor]:
    """Trunk height [N], velocities in the base frame [N, 3] and gravity in the base frame
    [N, 3] (unit), from the free joint at qpos ``adr`` / qvel ``dof``. MuJoCo's free-joint
    angular velocity is already in the body frame; its linear velocity is in the world's."""
    w, x, y, z = qpos[:, adr + 3], qpos[:, adr + 4], qpos[:, adr + 5], qpos[:, adr + 6]
    # Rotation body -> world, entries r_ij; the base frame's velocity is R^T v.
    r00, r01, r02 = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    r10, r11, r12 = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    r20, r21, r22 = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
    vx, vy, vz = qvel[:, dof], qvel[:, dof + 1], qvel[:, dof + 2]
    lin = torch.stack([r00 * vx + r10 * vy + r20 * vz, r01 * vx + r11 * vy + r21 * vz,
                       r02 * vx + r12 * vy + r22 * vz], -1)
    return {"height": qpos[:, adr + 2], "lin_vel": lin, "ang_vel": qvel[:, dof + 3 : dof + 6],
            "gravity": -torch.stack([r20, r21, r22], -1)}


@dataclass(frozen=True)
class LegServo:
    """The leg servos (a PD about the joint target, torque-limited) and the leg action's scale
    (target = stand + ``action_scale`` * action, within the joint ranges). A leg policy is
    trained under one and runs under it (``env.locomotion.leg_kp``, ``leg_kd``, ``action_scale``):
    robot.py's model carries the defaults, :meth:`apply` writes others into a compiled model."""

    kp: float = LEG_KP
    kd: float = LEG_KD
    action_scale: float = ACTION_SCALE

    def __post_init__(self):
        if not (self.kp > 0 and self.kd >= 0 and self.action_scale > 0):
            raise ValueError(f"leg servo needs kp > 0, kd >= 0 and action_scale > 0; got kp={self.kp!r}, "
                             f"kd={self.kd!r}, action_scale={self.action_scale!r}")

    def targets(self, action: torch.Tensor) -> torch.Tensor:
        """Leg joint targets [N, 12] of actions [N, 12] in [-1, 1]."""
        return torch.minimum(torch.maximum(STAND + self.action_scale * action, _LEG_LO), _LEG_HI)

    def torques(self, target: torch.Tensor, q: torch.Tensor, qd: torch.Tensor) -> torch.Tensor:
        """The servos' torques [N, 12] at joint targets ``target`` (the model's PD and limit)."""
        return (self.kp * (target - q) - self.kd * qd).clamp(-LEG_TORQUE, LEG_TORQUE)

    def apply(self, model: mujoco.MjModel, actuators) -> None:
        """Set these gains on leg actuators ``actuators`` (ids [..., 12], LEG_JOINTS order) of
        ``model``: force = kp (ctrl + q_stand - q) - kd qdot, as robot.py builds them."""
        params = leg_servo_params(self.kp, self.kd, stand_pose())
        for ids in np.asarray(actuators).reshape(-1, len(LEG_JOINTS)):
            model.actuator_gainprm[ids, 0] = params["gainprm"][0]
            for k, column in enumerate(params["biasprm"]):
                model.actuator_biasprm[ids, k] = column


def fallen(height: torch.Tensor, gravity: torch.Tensor, min_height: float, max_tilt: float) -> torch.Tensor:
    """Bool [N]: the trunk is below ``min_height`` (m) or tilted beyond ``max_tilt`` (rad)."""
    return (height < min_height) | (-gravity[:, 2] < math.cos(max_tilt))


def feet_air_time(air: torch.Tensor, contact: torch.Tensor, last_contact: torch.Tensor,
                  command: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """legged_gym's ``_reward_feet_air_time``: at touchdown each foot pays its air time minus
    AIR_TIME_TARGET, only under a planar command above 0.1 m/s. ``air`` [N, 4] (s) and the
    contacts [N, 4] of this and the last step; returns the term [N] and the new air times."""
    filt = contact | last_contact  # contact flickers between steps
    first = (air > 0) & filt
    air = air + POLICY_DT
    term = ((air - AIR_TIME_TARGET) * first).sum(-1) * (command[:, :2].norm(dim=-1) > 0.1)
    return term, air * ~filt


def reward_terms(base: dict, command, q, qd, last_qd, target, action, last_action, air_term, fell,
                 servo: LegServo, tracking_sigma: float) -> torch.Tensor:
    """[N, 1, len(LOCO_REWARD_TERMS)], raw (weights are the reward schedule's)."""
    lin, ang = base["lin_vel"], base["ang_vel"]
    lin_err = (command[:, 0] - lin[:, 0]) ** 2 + (command[:, 1] - lin[:, 1]) ** 2
    acc = (qd - last_qd) / POLICY_DT
    cols = [
        torch.exp(-lin_err / tracking_sigma),
        torch.exp(-((command[:, 2] - ang[:, 2]) ** 2) / tracking_sigma),
        lin[:, 2] ** 2,
        ang[:, 0] ** 2 + ang[:, 1] ** 2,
        base["gravity"][:, 0] ** 2 + base["gravity"][:, 1] ** 2,
        servo.torques(target, q, qd).pow(2).sum(-1),
        acc.pow(2).sum(-1),
        (action - last_action).pow(2).sum(-1),
        air_term,
        (qd.abs() - LEG_SPEED).clamp(0.0, 1.0).sum(-1),
        fell.float(),
    ]
    return torch.stack(cols, -1).unsqueeze(1)


def observation(base: dict, command, q, qd, last_action, arm_q) -> torch.Tensor:
    """[N, 1, LOCO_OBS_DIM] in the order of LOCO_OBS_SIZES (raw units; the trainer normalises)."""
    return torch.cat([base["lin_vel"], base["ang_vel"], base["gravity"], command, q - STAND, qd, last_action,
                      arm_q], -1).unsqueeze(1)


# --- sampling -----------------------------------------------------------------------------
def sample_commands(rng: torch.Generator, m: int, low, high, stand_share: float) -> torch.Tensor:
    """[m, 3] (vx, vy m/s, yaw rate rad/s) uniform in [low, high]; ``stand_share`` of them zero."""
    lo, hi = torch.tensor(low, dtype=torch.float32), torch.tensor(high, dtype=torch.float32)
    cmd = lo + (hi - lo) * torch.rand(m, 3, generator=rng)
    return cmd * (torch.rand(m, 1, generator=rng) >= stand_share)


def sample_arm_goals(rng: torch.Generator, m: int) -> torch.Tensor:
    """Arm joint goals [m, 6]: a random EE pose in the HL action's EE box (base frame, gripper
    down), moved into reach and solved by the closed-form IK (as the HL executors aim)."""
    lo, hi = torch.tensor(EE_LOW), torch.tensor(EE_HIGH)
    ee = lo + (hi - lo) * torch.rand(m, 4, generator=rng)
    q = arm_ik(clamp_reach(ee[:, :3]), ee[:, 3])
    return torch.minimum(torch.maximum(q, _ARM_LO), _ARM_HI)


def sample_uniform(rng: torch.Generator, m: int, bounds) -> torch.Tensor:
    lo, hi = float(bounds[0]), float(bounds[1])
    return lo + (hi - lo) * torch.rand(m, generator=rng)
