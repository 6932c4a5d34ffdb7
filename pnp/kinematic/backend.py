"""A fast kinematic backend of the PnP environment, in pure batched torch (``backend="kinematic"``).

It implements :class:`pnp.sim.backend.Backend` with no physics engine: every quantity is a
closed-form update of float32 tensors over all worlds and robots at once (no Python loop
over worlds). It produces the same :class:`pnp.task.PnPState` as the MuJoCo backend, so
actions, observations, reward terms, stage conditions and the success/fall/timeout rules
(all computed by ``pnp.task`` and ``envs.pnp_env``) are shared unchanged. This module
keeps the state (:class:`KinematicBackend`); the step is ``pnp.kinematic.step`` and the
arm's closed-form kinematics ``pnp.sim.arm_closed_form``.

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
  ``ArmKinematics.fk``) and costs ~25 elementwise ops. The DLS ``ArmKinematics.ik`` of
  the MuJoCo executor was measured too expensive here: 9 ms per iteration at 4096 rows
  on 2 cores (27 ms for 3 warm-started iterations), against ~0.1 ms for the closed form.
  Joint targets are then rate-limited to ``ARM_SPEED`` (4 rad/s, as the executor does)
  and clamped to ``ARM_RANGES``; the EE pose reported is the closed-form FK of the joint
  angles, so ``arm_q``, ``ee_pos`` and ``ee_rot`` are always mutually consistent (and
  the ``arm_q`` observation and the arm_default_pose / joint_limits terms meaningful).
  Targets high above and far from the shoulder need the wrist pitch j5 beyond its
  range (~20 % of uniformly random EE commands): j5 is clamped there, so the gripper
  tilts and the EE ends where the FK puts it, as the executor's DLS would compromise.
  ``arm_qd`` is the finite difference of ``arm_q`` over the step.
* **Fingers**: the opening of both fingers moves toward 0 (command > 0.5) or
  ``FINGER_STROKE`` at ``finger_speed`` (default 1.0 m/s: a full stroke in 0.07 s, within
  one HL step, as the MuJoCo fingers close).
  When closing fingers reach the bar radius while the EE is within ``GRASP_DIST`` of a
  handle bar (the one whose centre is nearest; ``pnp.task.geometry`` picks the same, except
  that of two robots at one handle the farther is assigned the other) and the closing
  axis is within ``GRASP_ALIGN`` of perpendicular to the bar, the handle is grasped:
  fingers stop at ``HANDLE_RADIUS`` and both pads report touch.
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
  With ``grasp_holds=True`` (off by default) the bar holds the hand instead, as pads
  squeezing a bar do: each holder's joints are re-solved (no rate limit) to put its EE at
  its grasp point on the box's new pose (resting for a lone holder, the pair's mean when
  both carry), and a grasp ends only when the gripper opens or that point is out of the
  arm's reach or joint ranges. The pair's box then does not slide on the floor either: it
  moves in x, y and yaw only once lifted ``LIFT_OFF`` (1 cm) off it. Without it, under a
  policy whose EE moves ~14 cm per step (the std floor) grasps lasted less than a step:
  285 of 285 were lost with the gripper still closed (measured with a lone holder's EE held
  at the bar's height, which only helps).
* **Free box**: falls under gravity (exact constant-acceleration update of z and vz,
  horizontal velocity kept while airborne), stops on the floor with zero velocity and
  rests there. A carried box cannot be pushed through the floor: the holder's EE height
  is clamped so the box bottom stays at or above z = 0.
* ``box_vel`` (world linear and angular velocity) is the finite difference of the box
  pose over the HL step.

Simplifications (with respect to the MuJoCo backend):

* No contacts: bases, legs, arm and gripper pass through the box, robots through each
  other (on MuJoCo robots do not collide either); the box is never pushed, only carried.
  Optionally (``box_blocks_base=True``, off by default) a base whose footprint
  (``pnp.task.FOOTPRINT_HALF``) would newly overlap the box's, while it does not hold the
  box, stays where it was for that step. On MuJoCo the legs hit the box and shove it;
  blocking is the cheaper stand-in (the scripted dual policy, which routes through the
  box, is tested without it). (The env's collision *term* is a
  geometric proxy computed by ``pnp.task`` and still works.)
* The box never tilts or swings: it stays level (yaw only), also when hanging from one
  handle, and it never slips in the pads. It never leaves the floor unless carried.
* The base never falls (``base_z`` is always ``STANDING_HEIGHT``), so the fall term and
  fall termination never fire; the base has no acceleration limits and no legs.
* The wrist roll j4 is always 0 (the closed-form IK branch); the EE lag replaces the
  executor's per-joint PD/rate dynamics at 50 Hz; no IK failure modes. The gripper yaw
  that carries the box is j1 - j6 (exact while the gripper is vertical, i.e. unless j5
  is at its limit).
* Box mass is stored but only matters through the dual-robot "heavy box" rule.
* ``push`` (external wrenches) is not modelled (``NotImplementedError``); ``displace_box``
  (a box moved and set down elsewhere, released) is. The backend never diverges
  (``step`` returns all False).
"""
from __future__ import annotations

import torch

from pnp.sim.arm_closed_form import arm_fk, arm_fk_columns, arm_ik
from pnp.sim.backend import Backend, Layout
from pnp.sim.box import HANDLE_HEIGHT, HANDLE_INSET, HANDLE_LEN
from pnp.kinematic.step import (
    EE_TAU, FINGER_SPEED, GRASP_ALIGN, GRAVITY, LIFT_OFF, KinematicParams, box_rotation, kinematic_step,
)
from pnp.sim.arm_ik import LW, SHOULDER
from pnp.sim.robot import ARM_DEFAULT, ARM_RANGES, FINGER_STROKE, STANDING_HEIGHT
from pnp.task import GRASP_DIST, HL_DT, PnPState

__all__ = ["EE_TAU", "FINGER_SPEED", "GRASP_ALIGN", "GRAVITY", "LIFT_OFF", "KinematicBackend", "KinematicParams",
           "arm_fk", "arm_ik", "kinematic_step"]


# get_state saves these; the rest of the state dict is derived.
_PRIMARY = ("bx", "by", "yaw", "base_vel", "q", "qd", "finger", "grasp", "handle", "rel_x", "rel_y", "rel_z", "rel_c",
            "rel_s", "box_x", "box_y", "box_z", "box_c", "box_s", "box_yaw", "box_vx", "box_vy", "box_vz", "box_vel",
            "box_size", "box_mass")


class KinematicBackend(Backend):
    """Kinematic PnP worlds in pure torch; see the module docstring for the model.

    The state is a dict of structure-of-arrays tensors (``self._st``). The PnPState fields
    read as attributes too (``backend.box_pos``, ``backend.arm_q``, ``backend.grasp``, ...).
    """

    def __init__(self, num_worlds: int, num_robots: int, ee_tau: float = EE_TAU, finger_speed: float = FINGER_SPEED,
                 dt: float = HL_DT, grasp_dist: float = GRASP_DIST, grasp_align: float = GRASP_ALIGN,
                 box_blocks_base: bool = False, grasp_holds: bool = False):
        if num_robots not in (1, 2):
            raise ValueError(f"num_robots must be 1 or 2, got {num_robots!r}")
        self.num_worlds, self.num_robots = N, R = num_worlds, num_robots
        self.params = KinematicParams(dt=float(dt), ee_tau=float(ee_tau), finger_speed=float(finger_speed),
                                      grasp_dist=float(grasp_dist), grasp_align=float(grasp_align),
                                      box_blocks_base=bool(box_blocks_base),
                                      grasp_holds=bool(grasp_holds) and num_robots == 2)
        f = dict(dtype=torch.float32)
        lim = torch.tensor(ARM_RANGES, **f)
        self.q_default = torch.tensor(ARM_DEFAULT, **f)
        z = lambda *shape: torch.zeros(*shape, **f)  # noqa: E731
        self._st = {
            # constants
            "zero": z(N, R), "zero_w": z(N), "one_w": torch.ones(N, **f),
            "q_low": lim[:, 0].clone(), "q_high": lim[:, 1].clone(),
            # robots: base pose and world velocity (vx, vy, yaw rate), arm joints, fingers
            "bx": z(N, R), "by": z(N, R), "yaw": z(N, R), "base_vel": z(N, R, 3),
            "q": self.q_default.expand(N, R, 6).clone(), "qd": z(N, R, 6),
            "finger": torch.full((N, R), FINGER_STROKE, **f),  # opening of each finger
            "grasp": torch.zeros(N, R, dtype=torch.bool),  # holding a handle
            "handle": torch.zeros(N, R, dtype=torch.bool),  # which: False handle0 (+x), True handle1 (-x)
            # box pose in the gripper's yaw frame at grasp time: x, y, z, cos and sin of yaw
            "rel_x": z(N, R), "rel_y": z(N, R), "rel_z": z(N, R), "rel_c": torch.ones(N, R, **f), "rel_s": z(N, R),
            # box (level): position, cos/sin of yaw and yaw, velocity while airborne, reported velocity
            "box_x": z(N), "box_y": z(N), "box_z": z(N), "box_c": torch.ones(N, **f), "box_s": z(N), "box_yaw": z(N),
            "box_vx": z(N), "box_vy": z(N), "box_vz": z(N), "box_vel": z(N, 6),
            "box_size": torch.ones(N, 3, **f), "box_mass": torch.ones(N, **f),
        }
        self._base_z = torch.full((N, R), STANDING_HEIGHT, **f)
        self._derive()

    # --- Backend API -----------------------------------------------------------------------
    def reset(self, worlds: torch.Tensor, layout: Layout) -> None:
        st, w = self._st, worlds.long()
        base = layout.base.float()
        st["bx"][w], st["by"][w], st["yaw"][w] = base[..., 0], base[..., 1], base[..., 2]
        size, xyz = layout.box_size.float(), layout.box_xy_yaw.float()
        st["box_x"][w], st["box_y"][w], st["box_z"][w] = xyz[:, 0], xyz[:, 1], size[:, 2] / 2
        st["box_yaw"][w], st["box_c"][w], st["box_s"][w] = xyz[:, 2], torch.cos(xyz[:, 2]), torch.sin(xyz[:, 2])
        st["box_size"][w] = size
        st["box_mass"][w] = layout.box_mass.float()
        st["q"][w] = self.q_default
        st["finger"][w] = FINGER_STROKE
        st["rel_c"][w] = 1.0
        for k in ("grasp", "handle", "rel_x", "rel_y", "rel_z", "rel_s", "box_vx", "box_vy", "box_vz", "base_vel",
                  "box_vel", "qd"):
            st[k][w] = 0
        self._derive()

    def step(self, action: torch.Tensor) -> torch.Tensor:
        self._st = kinematic_step(self._st, action.float(), self.params)
        self._make_views()
        return torch.zeros(self.num_worlds, dtype=torch.bool)

    def displace_box(self, worlds: torch.Tensor, offsets: torch.Tensor) -> None:
        st, w = self._st, worlds.long()
        moved = torch.zeros(self.num_worlds, dtype=torch.bool)
        moved[w] = True
        shift = torch.zeros(self.num_worlds, 2)
        shift[w] = offsets.float()
        # New tensors, not in-place writes: earlier states may share these.
        st["box_x"], st["box_y"] = st["box_x"] + shift[:, 0], st["box_y"] + shift[:, 1]
        st["box_z"] = torch.where(moved, st["box_size"][:, 2] * 0.5, st["box_z"])
        for k in ("box_vx", "box_vy", "box_vz"):
            st[k] = torch.where(moved, 0.0, st[k])
        st["box_vel"] = torch.where(moved.unsqueeze(-1), 0.0, st["box_vel"])
        st["grasp"] = st["grasp"] & ~moved.unsqueeze(-1)  # closed fingers now hold nothing
        self._derive()

    def state(self, goal: torch.Tensor, init_goal_dist: torch.Tensor, grasp_cmd: torch.Tensor) -> PnPState:
        return PnPState(**self._views, base_z=self._base_z, box_size=self._st["box_size"], goal=goal,
                        init_goal_dist=init_goal_dist, grasp_cmd=grasp_cmd)

    def get_state(self) -> dict[str, torch.Tensor]:
        return {k: self._st[k].clone() for k in _PRIMARY}

    def set_state(self, state: dict[str, torch.Tensor]) -> None:
        missing = [k for k in _PRIMARY if k not in state]
        if missing:
            raise KeyError(f"kinematic backend state is missing {missing}")
        for k in _PRIMARY:
            self._st[k] = state[k].contiguous().clone()
        # (a state saved while the removed ``slip`` option existed also holds ee_v* and slip_rng: unread)
        self._derive()

    def __getattr__(self, name):
        # Read access to the PnPState fields and the state tensors (``backend.box_pos``).
        d = self.__dict__
        for src in (d.get("_views"), d.get("_st")):
            if src is not None and name in src:
                return src[name]
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    # --- internals ---------------------------------------------------------------------------
    def _derive(self):
        """Recompute everything derived from the primary state (after a reset or restore)."""
        st = self._st
        st.update(arm_fk_columns(st["q"], st["yaw"], st["bx"], st["by"]))
        st["box_rot"] = box_rotation(st["box_c"], st["box_s"], st["zero_w"], st["one_w"])
        size = st["box_size"]
        st["box_hc"] = size[:, 2] * 0.5
        st["box_hc_eps"] = st["box_hc"] + 1e-6
        st["box_hz"] = st["box_hc"] + HANDLE_HEIGHT  # bar axis above the box centre
        st["box_hx"] = size[:, 0:1] * 0.5 - HANDLE_INSET  # bar axis from the centre along x, [N, 1]
        st["box_half_len"] = (0.6 * size[:, 1:2]).clamp(max=HANDLE_LEN) * 0.5
        # Lowest wrist-centre height (IK coordinates) that keeps a held box on or above the floor.
        st["min_wz"] = (st["box_hc"] + (LW - SHOULDER[2] - STANDING_HEIGHT)).unsqueeze(1)
        self._make_views()

    def _make_views(self):
        """PnPState fields, world-first and contiguous: the shared task functions ran ~25 %
        slower on permuted views of component-first tensors than this assembly costs."""
        st = self._st
        N, R = self.num_worlds, self.num_robots
        self._views = {
            "base": torch.stack([st["bx"], st["by"], st["yaw"]], -1), "base_vel": st["base_vel"],
            "arm_q": st["q"], "arm_qd": st["qd"],
            "finger_q": st["finger"].unsqueeze(-1).expand(N, R, 2), "touch": st["grasp"].unsqueeze(-1).expand(N, R, 2),
            "ee_pos": torch.stack([st["ee_x"], st["ee_y"], st["ee_z"]], -1), "ee_rot": st["ee_rot"],
            "box_pos": torch.stack([st["box_x"], st["box_y"], st["box_z"]], -1), "box_rot": st["box_rot"],
            "box_vel": st["box_vel"],
        }
