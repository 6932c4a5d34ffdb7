"""A fast kinematic backend of the PnP environment, in pure batched torch (``backend="kinematic"``).

It implements :class:`pnp.backend.Backend` with no physics engine: every quantity is a
closed-form update of float32 tensors over all worlds and robots at once (no Python loop
over worlds). It produces the same :class:`pnp.task.PnPState` as the MuJoCo backend, so
actions, observations, reward terms, stage conditions and the success/fall/timeout rules
(all computed by ``pnp.task`` and ``envs.pnp_env``) are shared unchanged.

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
  moves in x, y and yaw only once lifted ``LIFT_OFF`` (1 cm) off it. Without it (with
  ``lone_holder_pinned``) a policy whose EE moves ~14 cm per step (the std floor) lost 285 of
  285 grasps with the gripper still closed, after less than a step on average (stop 17).
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
* ``push`` (external wrenches) is not modelled (``NotImplementedError``). The backend
  never diverges (``step`` returns all False).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from pnp.backend import Backend, Layout
from pnp.box import HANDLE_HEIGHT, HANDLE_INSET, HANDLE_LEN, HANDLE_RADIUS
from pnp.kinematics import L1, L2, LW, REACH_MAX, REACH_MIN, SHOULDER
from pnp.robot import ARM_DEFAULT, ARM_RANGES, ARM_SPEED, FINGER_STROKE, STANDING_HEIGHT
from pnp.task import FOOTPRINT_HALF, GRASP_DIST, HL_DT, PnPState, rects_overlap

GRAVITY = 9.81  # m/s^2
EE_TAU = 0.08  # s, first-order lag of the EE toward its commanded pose
# m/s per finger. MuJoCo's position-actuated fingers close their full 7 cm stroke within one
# HL step (measured: 0.07 -> 7e-5 m); at 0.5 m/s a grasp needed two closed commands in a row,
# which a stochastic policy almost never samples.
FINGER_SPEED = 1.0
LIFT_OFF = 0.01  # m, grasp_holds: a pair's box slides in x, y, yaw only with its bottom this far up
GRASP_ALIGN = 0.7  # grasp needs 1 - |cos(closing axis, bar axis)| above this (~17 deg)
_Q6_WIND = ARM_RANGES[5][1] - 0.1  # flip the gripper's half-turn choice before j6 reaches its limit


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
    down with gripper yaw ``yaw`` (as in ``pnp.kinematics.gripper_down_rotation``)."""
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


def _wrap(a: torch.Tensor) -> torch.Tensor:
    return torch.remainder(a + math.pi, 2 * math.pi) - math.pi


@dataclass(frozen=True)
class KinematicParams:
    """Constants of the kinematic model (see the module docstring)."""

    dt: float = HL_DT
    ee_tau: float = EE_TAU
    finger_speed: float = FINGER_SPEED
    grasp_dist: float = GRASP_DIST
    grasp_align: float = GRASP_ALIGN
    gravity: float = GRAVITY
    box_blocks_base: bool = False  # True: a base does not step into a box it does not hold
    lone_holder_pinned: bool = False  # True: two robots; a lone holder's EE cannot rise off the resting box
    grasp_holds: bool = False  # True: two robots; a closed gripper keeps its bar, its EE follows the grasp point


# Implementation notes (speed, measured on 2 CPU cores at N = 4096): the state is mostly
# structure-of-arrays, one contiguous [N, R] (or [N]) tensor per component, so each op is
# a plain contiguous elementwise loop (~2-4 us); small reductions (norm, sum over a last
# dim of 2-3), batched 3x3 matmuls, tiny GEMMs and transposing copies cost 10-100x more
# and are avoided. The [N, R, k]-shaped PnPState fields are assembled once per step
# (torch.stack along the last dim); joints stay [N, R, 6]. A step is ~250 torch ops.
_W_OFF = torch.tensor([-SHOULDER[0], -SHOULDER[1], LW - SHOULDER[2]])  # EE -> wrist centre rel. to the shoulder


def _fk(q: torch.Tensor, yaw: torch.Tensor, bx: torch.Tensor, by: torch.Tensor) -> dict[str, torch.Tensor]:
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


def kinematic_step(st: dict[str, torch.Tensor], action: torch.Tensor, p: KinematicParams) -> dict[str, torch.Tensor]:
    """One HL step of every world: a pure function of the state dict (see
    :class:`KinematicBackend`) and the clipped action [N, R, 8]; returns the new state dict."""
    dt = p.dt
    alpha = 1.0 - math.exp(-dt / p.ee_tau) if p.ee_tau > 0 else 1.0
    R = action.shape[1]
    vx, vy, wz = action[..., 0], action[..., 1], action[..., 2]
    closed = action[..., 7] > 0.5
    zero, zero_w, one_w = st["zero"], st["zero_w"], st["one_w"]

    # Base: constant body-frame twist over the step, integrated exactly (an arc).
    yaw0 = st["yaw"]
    dyaw = wz * dt
    k = torch.sinc(wz * (dt / (2 * math.pi))) * dt
    mid = torch.add(yaw0, dyaw, alpha=0.5)
    cm, sm = torch.cos(mid), torch.sin(mid)
    kvx, kvy = k * vx, k * vy
    bx = st["bx"] + torch.addcmul(cm * kvx, sm, kvy, value=-1)
    by = st["by"] + torch.addcmul(sm * kvx, cm, kvy)
    yaw1 = _wrap(yaw0 + dyaw)
    if p.box_blocks_base:
        # The footprint (pnp.task.FOOTPRINT_HALF) would newly overlap the box's: the legs
        # hit it, the base stays (a robot already overlapping may move, to get out).
        block = _box_overlap(st, bx, by, yaw1) & ~_box_overlap(st, st["bx"], st["by"], yaw0) & ~st["grasp"]
        bx, by, yaw1 = torch.where(block, st["bx"], bx), torch.where(block, st["by"], by), torch.where(block, yaw0, yaw1)
        vx, vy, wz = vx * ~block, vy * ~block, wz * ~block

    # Opening the gripper lets go.
    grasp = st["grasp"] & closed

    # EE target: first-order lag toward the command (base frame), half-turn yaw choice.
    q_old = st["q"]
    q6_old = q_old[..., 5]
    yaw_now = q_old[..., 0] - q6_old
    d = torch.remainder(action[..., 6] - yaw_now + math.pi / 2, math.pi) - math.pi / 2
    # ... unless that would wind j6 (= j1 - yaw) past its range: take the other half turn.
    d = torch.add(d, torch.round((q6_old - d) * (0.5 / _Q6_WIND)), alpha=math.pi)
    yaw_t = torch.add(yaw_now, d, alpha=alpha)
    wx, wy, wzc = (torch.lerp(st["ee_b"], action[..., 3:6], alpha) + _W_OFF).unbind(-1)  # wrist centre rel. to shoulder
    wx, wy, wzc, dr2 = _in_reach(wx, wy, wzc)
    # A held box stays above the floor: EE height >= c/2 - (box z - EE z at grasp).
    wzc = torch.where(grasp, torch.maximum(wzc, st["min_wz"] - st["rel_z"]), wzc)
    if p.lone_holder_pinned:
        # The heavy box outweighs one arm: a lone holder's EE stays at the height the box
        # rests at, so it keeps its grasp while it waits (else lifting alone slid the EE off
        # the bar, and two robots never held at once; stop 16).
        lone = grasp & ~(grasp.flip(1) & (st["handle"] != st["handle"].flip(1)))
        wzc = torch.where(lone, torch.minimum(wzc, st["min_wz"] - st["rel_z"]), wzc)
    # Closed-form IK (see arm_ik), then the joint rate limit and the joint ranges.
    q_des = _ik_wrist(wx, wy, wzc, dr2, yaw_t, zero)
    dq_max = ARM_SPEED * dt
    q = torch.clamp(q_old + (q_des - q_old).clamp(-dq_max, dq_max), st["q_low"], st["q_high"])
    arm = _fk(q, yaw1, bx, by)
    cy, sy, cg, sg = arm["cy"], arm["sy"], arm["cg"], arm["sg"]
    ee_x, ee_y, ee_z = arm["ee_x"], arm["ee_y"], arm["ee_z"]

    # Box: carried, resting or falling.
    box_x, box_y, box_z, c0, s0 = st["box_x"], st["box_y"], st["box_z"], st["box_c"], st["box_s"]
    hc = st["box_hc"]
    rx, ry, rz, rc, rs = st["rel_x"], st["rel_y"], st["rel_z"], st["rel_c"], st["rel_s"]
    imp_x = torch.addcmul(torch.addcmul(ee_x, cg, rx), sg, ry, value=-1)  # box pose each gripper implies
    imp_y = torch.addcmul(torch.addcmul(ee_y, sg, rx), cg, ry)
    imp_z = ee_z + rz
    imp_c = torch.addcmul(cg * rc, sg, rs, value=-1)
    imp_s = torch.addcmul(sg * rc, cg, rs)
    if R == 1:
        carried = grasp[:, 0]
        cx, cy_, cz, cc, cs = imp_x[:, 0], imp_y[:, 0], imp_z[:, 0], imp_c[:, 0], imp_s[:, 0]
    else:  # the mean of the poses both grippers imply (circular mean for yaw)
        carried = grasp[:, 0] & grasp[:, 1] & (st["handle"][:, 0] != st["handle"][:, 1])
        cx, cy_ = (imp_x[:, 0] + imp_x[:, 1]) * 0.5, (imp_y[:, 0] + imp_y[:, 1]) * 0.5
        cz = (imp_z[:, 0] + imp_z[:, 1]) * 0.5
        cc, cs = imp_c[:, 0] + imp_c[:, 1], imp_s[:, 0] + imp_s[:, 1]
        inv = torch.rsqrt(torch.addcmul(cc * cc, cs, cs).clamp(min=1e-12))
        cc, cs = cc * inv, cs * inv
    airborne = box_z > st["box_hc_eps"]
    # With grasp_holds the pair's box does not slide on the floor (friction holds it, as for
    # a lone holder): it moves in x, y and yaw only once lifted LIFT_OFF off. Else two
    # holders dragged it to the goal after one brief lift, which counted as success (stop 17).
    moves = carried & (cz > hc + LIFT_OFF) if p.grasp_holds and R == 2 else carried
    z_fall = torch.add(box_z, st["box_vz"], alpha=dt) - 0.5 * p.gravity * dt * dt
    flying = airborne & (z_fall > hc)
    nx = torch.where(moves, cx, torch.where(airborne, torch.add(box_x, st["box_vx"], alpha=dt), box_x))
    ny = torch.where(moves, cy_, torch.where(airborne, torch.add(box_y, st["box_vy"], alpha=dt), box_y))
    nz = torch.maximum(torch.where(carried, cz, torch.where(airborne, z_fall, box_z)), hc)
    nc, ns = torch.where(moves, cc, c0), torch.where(moves, cs, s0)
    lin_x, lin_y, lin_z = (nx - box_x) * (1.0 / dt), (ny - box_y) * (1.0 / dt), (nz - box_z) * (1.0 / dt)
    box_yaw = torch.where(moves, torch.atan2(cs, cc), st["box_yaw"])
    wz_box = _wrap(box_yaw - st["box_yaw"]) * (1.0 / dt)

    if p.grasp_holds and R == 2:
        # The bar holds the hand: a holder's EE goes to its grasp point on the box's new pose
        # (static for a lone holder, the pair's mean when both carry), as far as reach allows.
        q = torch.where(grasp.unsqueeze(-1), _hold_q(st, q, nx, ny, nz, nc, ns, bx, by, yaw1, zero), q)
        arm = _fk(q, yaw1, bx, by)
        cy, sy, cg, sg = arm["cy"], arm["sy"], arm["cg"], arm["sg"]
        ee_x, ee_y, ee_z = arm["ee_x"], arm["ee_y"], arm["ee_z"]

    # Handle bars in the (level) box frame: EE distance to both bars.
    ncu, nsu = nc.unsqueeze(1), ns.unsqueeze(1)
    dx, dy = ee_x - nx.unsqueeze(1), ee_y - ny.unsqueeze(1)
    lx = torch.addcmul(ncu * dx, nsu, dy)
    ly = torch.addcmul(ncu * dy, nsu, dx, value=-1)
    lz = ee_z - (nz + st["box_hz"]).unsqueeze(1)
    ex = (ly.abs() - st["box_half_len"]).clamp(min=0.0)
    common = torch.addcmul(lz * lz, ex, ex)
    hx = st["box_hx"]
    dxp, dxm = lx - hx, lx + hx
    bar_p = torch.sqrt(torch.addcmul(common, dxp, dxp))
    bar_m = torch.sqrt(torch.addcmul(common, dxm, dxm))
    near_m = lx < 0  # handle 1 (-x) has the nearer centre
    held_m = st["handle"]
    grasp = grasp & (torch.where(held_m, bar_m, bar_p) < p.grasp_dist)
    # Closing axis against the bar axis: 1 - |cos(gripper yaw - box yaw)|.
    align = 1.0 - torch.addcmul(cg * ncu, sg, nsu).abs()

    # Fingers; a new grasp when closing fingers reach a bar the EE is on (fingers held on a
    # bar, or already shut, do not pass the bar radius).
    f0 = st["finger"]
    fstep = p.finger_speed * dt
    f1 = torch.where(closed, (f0 - fstep).clamp(min=0.0), (f0 + fstep).clamp(max=FINGER_STROKE))
    new = (f0 > HANDLE_RADIUS) & (f1 <= HANDLE_RADIUS) & (torch.where(near_m, bar_m, bar_p) < p.grasp_dist)
    new = new & (align > p.grasp_align)
    # Box pose in the gripper's yaw frame, recorded at grasp time.
    bxr, byr = nx.unsqueeze(1) - ee_x, ny.unsqueeze(1) - ee_y
    out = dict(st)
    out.update(
        bx=bx, by=by, yaw=yaw1, q=q, qd=(q - q_old) * (1.0 / dt),
        base_vel=torch.stack([torch.addcmul(cy * vx, sy, vy, value=-1), torch.addcmul(sy * vx, cy, vy), wz], -1),
        finger=torch.where(grasp | new, HANDLE_RADIUS, f1), grasp=grasp | new, handle=torch.where(new, near_m, held_m),
        rel_x=torch.where(new, torch.addcmul(cg * bxr, sg, byr), rx),
        rel_y=torch.where(new, torch.addcmul(cg * byr, sg, bxr, value=-1), ry),
        rel_z=torch.where(new, nz.unsqueeze(1) - ee_z, rz),
        rel_c=torch.where(new, torch.addcmul(ncu * cg, nsu, sg), rc),
        rel_s=torch.where(new, torch.addcmul(nsu * cg, ncu, sg, value=-1), rs),
        box_x=nx, box_y=ny, box_z=nz, box_c=nc, box_s=ns, box_yaw=box_yaw,
        box_vx=torch.where(carried, lin_x, st["box_vx"] * flying),
        box_vy=torch.where(carried, lin_y, st["box_vy"] * flying),
        box_vz=torch.where(carried, lin_z, (st["box_vz"] - p.gravity * dt) * flying),
        box_vel=torch.stack([lin_x, lin_y, lin_z, zero_w, zero_w, wz_box], -1),
        box_rot=_box_rotation(nc, ns, zero_w, one_w), **arm,
    )
    return out


def _in_reach(wx, wy, wzc):
    """A wrist centre relative to the shoulder scaled onto the reachable shell
    [REACH_MIN, REACH_MAX]; returns it and its horizontal distance squared."""
    dr2 = torch.addcmul(wx * wx, wy, wy)
    n2 = torch.addcmul(dr2, wzc, wzc)
    f2 = n2.clamp(REACH_MIN**2, REACH_MAX**2) / n2.clamp(min=1e-12)
    f = torch.sqrt(f2)
    return wx * f, wy * f, wzc * f, dr2 * f2


def _ik_wrist(wx, wy, wzc, dr2, yaw_t, zero):
    """Joint targets [N, R, 6] for a wrist centre (wx, wy, wzc) relative to the shoulder
    (dr2 = wx^2 + wy^2, within reach) and gripper yaw ``yaw_t`` (base frame), as arm_ik."""
    c3 = ((torch.addcmul(dr2, wzc, wzc) - (L1 * L1 + L2 * L2)) * (1.0 / (2 * L1 * L2))).clamp(-1.0, 1.0)
    q3 = -torch.acos(c3)
    q2 = torch.atan2(-wzc, torch.sqrt(dr2)) - torch.atan2(L2 * torch.sin(q3), L2 * c3 + L1)
    q1 = torch.atan2(wy, wx)
    return torch.stack([q1, q2, q3, zero, (math.pi / 2 - q2) - q3, q1 - yaw_t], -1)


def _hold_q(st, q, nx, ny, nz, nc, ns, bx, by, yaw, zero) -> torch.Tensor:
    """Joints [N, R, 6] that put each robot's EE at its grasp point on the box at (nx, ny, nz)
    with yaw (nc, ns), clamped to reach and the joint ranges (no rate limit: the box drags it)."""
    rx, ry, rc, rs = st["rel_x"], st["rel_y"], st["rel_c"], st["rel_s"]
    ncu, nsu = nc.unsqueeze(1), ns.unsqueeze(1)
    gc, gs = torch.addcmul(ncu * rc, nsu, rs), torch.addcmul(nsu * rc, ncu, rs, value=-1)  # gripper yaw = box yaw - rel
    dx = nx.unsqueeze(1) - torch.addcmul(gc * rx, gs, ry, value=-1) - bx  # grasp point - base, world
    dy = ny.unsqueeze(1) - torch.addcmul(gs * rx, gc, ry) - by
    dz = nz.unsqueeze(1) - st["rel_z"] - STANDING_HEIGHT
    c, s = torch.cos(yaw), torch.sin(yaw)
    ex, ey = torch.addcmul(c * dx, s, dy), torch.addcmul(c * dy, s, dx, value=-1)  # base frame
    wx, wy, wzc, dr2 = _in_reach(ex + _W_OFF[0], ey + _W_OFF[1], dz + _W_OFF[2])
    q_h = _ik_wrist(wx, wy, wzc, dr2, torch.atan2(gs, gc) - yaw, zero)
    q6 = q[..., 5] + _wrap(q_h[..., 5] - q[..., 5])  # the same gripper yaw, nearest the current j6
    q_h = torch.cat([q_h[..., :5], q6.unsqueeze(-1)], -1)
    return torch.clamp(q_h, st["q_low"], st["q_high"])


def _box_overlap(st: dict[str, torch.Tensor], bx: torch.Tensor, by: torch.Tensor, yaw: torch.Tensor) -> torch.Tensor:
    """[N, R]: a base at (bx, by, yaw) has its footprint overlapping the (level) box's."""
    c, s = torch.cos(yaw), torch.sin(yaw)
    dx, dy = st["box_x"].unsqueeze(1) - bx, st["box_y"].unsqueeze(1) - by
    bc, bs = st["box_c"].unsqueeze(1), st["box_s"].unsqueeze(1)
    size = st["box_size"]
    return rects_overlap(c * dx + s * dy, c * dy - s * dx, c * bc + s * bs, c * bs - s * bc,
                          size[:, 0:1] * 0.5, size[:, 1:2] * 0.5, *FOOTPRINT_HALF)


def _box_rotation(c: torch.Tensor, s: torch.Tensor, zero: torch.Tensor, one: torch.Tensor) -> torch.Tensor:
    return torch.stack([c, -s, zero, s, c, zero, zero, zero, one], -1).unflatten(-1, (3, 3))


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
                 box_blocks_base: bool = False, lone_holder_pinned: bool = False, grasp_holds: bool = False):
        if num_robots not in (1, 2):
            raise ValueError(f"num_robots must be 1 or 2, got {num_robots!r}")
        self.num_worlds, self.num_robots = N, R = num_worlds, num_robots
        self.params = KinematicParams(dt=float(dt), ee_tau=float(ee_tau), finger_speed=float(finger_speed),
                                      grasp_dist=float(grasp_dist), grasp_align=float(grasp_align),
                                      box_blocks_base=bool(box_blocks_base),
                                      lone_holder_pinned=bool(lone_holder_pinned) and num_robots == 2,
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
        st.update(_fk(st["q"], st["yaw"], st["bx"], st["by"]))
        st["box_rot"] = _box_rotation(st["box_c"], st["box_s"], st["zero_w"], st["one_w"])
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
