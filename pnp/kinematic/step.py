"""One HL step of the kinematic backend's worlds (``pnp.kinematic.backend``, whose docstring
describes the model): :func:`kinematic_step`, a pure function of the backend's state dict
and the action, with the model's constants (:class:`KinematicParams`)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from pnp.sim.arm_closed_form import EE_TO_WRIST, arm_fk_columns, ik_wrist, wrap_angle, wrist_in_reach
from pnp.sim.box import HANDLE_RADIUS
from pnp.sim.robot import ARM_RANGES, ARM_SPEED, FINGER_STROKE, STANDING_HEIGHT
from pnp.task.geometry import FOOTPRINT_HALF, GRASP_DIST, rects_overlap
from pnp.task.state import HL_DT

GRAVITY = 9.81  # m/s^2
EE_TAU = 0.08  # s, first-order lag of the EE toward its commanded pose
# m/s per finger. MuJoCo's position-actuated fingers close their full 7 cm stroke within one
# HL step (measured: 0.07 -> 7e-5 m); at 0.5 m/s a grasp needed two closed commands in a row,
# which a stochastic policy almost never samples.
FINGER_SPEED = 1.0
LIFT_OFF = 0.01  # m, grasp_holds: a pair's box slides in x, y, yaw only with its bottom this far up
GRASP_ALIGN = 0.7  # grasp needs 1 - |cos(closing axis, bar axis)| above this (~17 deg)
_Q6_WIND = ARM_RANGES[5][1] - 0.1  # flip the gripper's half-turn choice before j6 reaches its limit


@dataclass(frozen=True)
class KinematicParams:
    """Constants of the kinematic model (``pnp.kinematic.backend`` describes it)."""

    dt: float = HL_DT
    ee_tau: float = EE_TAU
    finger_speed: float = FINGER_SPEED
    grasp_dist: float = GRASP_DIST
    grasp_align: float = GRASP_ALIGN
    gravity: float = GRAVITY
    box_blocks_base: bool = False  # True: a base does not step into a box it does not hold
    grasp_holds: bool = False  # True: two robots; a closed gripper keeps its bar, its EE follows the grasp point


# Implementation notes (speed, measured on 2 CPU cores at N = 4096): the state is mostly
# structure-of-arrays, one contiguous [N, R] (or [N]) tensor per component, so each op is
# a plain contiguous elementwise loop (~2-4 us); small reductions (norm, sum over a last
# dim of 2-3), batched 3x3 matmuls, tiny GEMMs and transposing copies cost 10-100x more
# and are avoided. The [N, R, k]-shaped PnPState fields are assembled once per step
# (torch.stack along the last dim); joints stay [N, R, 6]. A step is ~250 torch ops.


def kinematic_step(st: dict[str, torch.Tensor], action: torch.Tensor, p: KinematicParams) -> dict[str, torch.Tensor]:
    """One HL step of every world: a pure function of the state dict (see
    ``pnp.kinematic.backend.KinematicBackend``) and the clipped action [N, R, 8]; returns the
    new state dict."""
    dt = p.dt
    alpha = 1.0 - math.exp(-dt / p.ee_tau) if p.ee_tau > 0 else 1.0
    R = action.shape[1]
    closed = action[..., 7] > 0.5
    zero, zero_w, one_w = st["zero"], st["zero_w"], st["one_w"]
    bx, by, yaw1, vx, vy, wz = _move_bases(st, action, p)
    grasp = st["grasp"] & closed  # opening the gripper lets go
    q_old = st["q"]
    q = _arm_joints(st, action, grasp, alpha, zero, dt)
    arm = arm_fk_columns(q, yaw1, bx, by)
    box = _move_box(st, arm, grasp, R, p)
    nx, ny, nz, nc, ns = box["nx"], box["ny"], box["nz"], box["nc"], box["ns"]
    if p.grasp_holds and R == 2:
        # The bar holds the hand: a holder's EE goes to its grasp point on the box's new pose
        # (static for a lone holder, the pair's mean when both carry), as far as reach allows.
        q = torch.where(grasp.unsqueeze(-1), _hold_q(st, q, nx, ny, nz, nc, ns, bx, by, yaw1, zero), q)
        arm = arm_fk_columns(q, yaw1, bx, by)
    cy, sy, cg, sg = arm["cy"], arm["sy"], arm["cg"], arm["sg"]
    ee_x, ee_y, ee_z = arm["ee_x"], arm["ee_y"], arm["ee_z"]
    grasp, new, near_m, f1 = _grasp_and_fingers(st, arm, box, grasp, closed, p)
    held_m, carried, flying = st["handle"], box["carried"], box["flying"]
    lin_x, lin_y, lin_z = box["lin_x"], box["lin_y"], box["lin_z"]
    ncu, nsu = nc.unsqueeze(1), ns.unsqueeze(1)
    rx, ry, rz, rc, rs = st["rel_x"], st["rel_y"], st["rel_z"], st["rel_c"], st["rel_s"]
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
        box_x=nx, box_y=ny, box_z=nz, box_c=nc, box_s=ns, box_yaw=box["box_yaw"],
        box_vx=torch.where(carried, lin_x, st["box_vx"] * flying),
        box_vy=torch.where(carried, lin_y, st["box_vy"] * flying),
        box_vz=torch.where(carried, lin_z, (st["box_vz"] - p.gravity * dt) * flying),
        box_vel=torch.stack([lin_x, lin_y, lin_z, zero_w, zero_w, box["wz_box"]], -1),
        box_rot=box_rotation(nc, ns, zero_w, one_w), **arm,
    )
    return out


def _move_bases(st, action, p: KinematicParams):
    """Each base under a constant body-frame twist over the step, integrated exactly (an arc);
    returns its new pose and the twist it moved with (zero where a box blocked it)."""
    dt = p.dt
    vx, vy, wz = action[..., 0], action[..., 1], action[..., 2]
    yaw0 = st["yaw"]
    dyaw = wz * dt
    k = torch.sinc(wz * (dt / (2 * math.pi))) * dt
    mid = torch.add(yaw0, dyaw, alpha=0.5)
    cm, sm = torch.cos(mid), torch.sin(mid)
    kvx, kvy = k * vx, k * vy
    bx = st["bx"] + torch.addcmul(cm * kvx, sm, kvy, value=-1)
    by = st["by"] + torch.addcmul(sm * kvx, cm, kvy)
    yaw1 = wrap_angle(yaw0 + dyaw)
    if p.box_blocks_base:
        # The footprint (pnp.task.FOOTPRINT_HALF) would newly overlap the box's: the legs
        # hit it, the base stays (a robot already overlapping may move, to get out).
        block = _box_overlap(st, bx, by, yaw1) & ~_box_overlap(st, st["bx"], st["by"], yaw0) & ~st["grasp"]
        bx, by, yaw1 = torch.where(block, st["bx"], bx), torch.where(block, st["by"], by), torch.where(block, yaw0, yaw1)
        vx, vy, wz = vx * ~block, vy * ~block, wz * ~block
    return bx, by, yaw1, vx, vy, wz


def _arm_joints(st, action, grasp, alpha: float, zero, dt: float) -> torch.Tensor:
    """The arm's joints [N, R, 6] after the step: the EE target lags toward the command (base
    frame) with a half-turn yaw choice, is scaled into reach, solved in closed form, then
    rate-limited and clamped to the joint ranges."""
    q_old = st["q"]
    q6_old = q_old[..., 5]
    yaw_now = q_old[..., 0] - q6_old
    d = torch.remainder(action[..., 6] - yaw_now + math.pi / 2, math.pi) - math.pi / 2
    # ... unless that would wind j6 (= j1 - yaw) past its range: take the other half turn.
    d = torch.add(d, torch.round((q6_old - d) * (0.5 / _Q6_WIND)), alpha=math.pi)
    yaw_t = torch.add(yaw_now, d, alpha=alpha)
    # Wrist centre relative to the shoulder, scaled into reach.
    wx, wy, wzc = (torch.lerp(st["ee_b"], action[..., 3:6], alpha) + EE_TO_WRIST).unbind(-1)
    wx, wy, wzc, dr2 = wrist_in_reach(wx, wy, wzc)
    # A held box stays above the floor: EE height >= c/2 - (box z - EE z at grasp).
    wzc = torch.where(grasp, torch.maximum(wzc, st["min_wz"] - st["rel_z"]), wzc)
    q_des = ik_wrist(wx, wy, wzc, dr2, yaw_t, zero)  # as arm_ik
    dq_max = ARM_SPEED * dt
    return torch.clamp(q_old + (q_des - q_old).clamp(-dq_max, dq_max), st["q_low"], st["q_high"])


def _move_box(st, arm, grasp, R: int, p: KinematicParams) -> dict[str, torch.Tensor]:
    """The box carried, resting or falling: its new pose (nx, ny, nz, nc, ns, box_yaw), its
    velocity over the step, and whether it was carried, moved and is still flying."""
    dt = p.dt
    cg, sg, ee_x, ee_y, ee_z = arm["cg"], arm["sg"], arm["ee_x"], arm["ee_y"], arm["ee_z"]
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
    # holders dragged it to the goal after one brief lift, which counted as success.
    moves = carried & (cz > hc + LIFT_OFF) if p.grasp_holds and R == 2 else carried
    z_fall = torch.add(box_z, st["box_vz"], alpha=dt) - 0.5 * p.gravity * dt * dt
    nx = torch.where(moves, cx, torch.where(airborne, torch.add(box_x, st["box_vx"], alpha=dt), box_x))
    ny = torch.where(moves, cy_, torch.where(airborne, torch.add(box_y, st["box_vy"], alpha=dt), box_y))
    nz = torch.maximum(torch.where(carried, cz, torch.where(airborne, z_fall, box_z)), hc)
    box_yaw = torch.where(moves, torch.atan2(cs, cc), st["box_yaw"])
    return {"nx": nx, "ny": ny, "nz": nz, "nc": torch.where(moves, cc, c0), "ns": torch.where(moves, cs, s0),
            "box_yaw": box_yaw, "wz_box": wrap_angle(box_yaw - st["box_yaw"]) * (1.0 / dt),
            "lin_x": (nx - box_x) * (1.0 / dt), "lin_y": (ny - box_y) * (1.0 / dt), "lin_z": (nz - box_z) * (1.0 / dt),
            "carried": carried, "flying": airborne & (z_fall > hc)}


def _grasp_and_fingers(st, arm, box, grasp, closed, p: KinematicParams):
    """The grasps kept (EE within ``grasp_dist`` of its bar), the new ones (closing fingers
    reach a bar the EE is on, aligned across it; fingers held on a bar, or already shut, do
    not pass the bar radius), which handle is nearer, and the fingers' new opening."""
    cg, sg, ee_x, ee_y, ee_z = arm["cg"], arm["sg"], arm["ee_x"], arm["ee_y"], arm["ee_z"]
    ncu, nsu = box["nc"].unsqueeze(1), box["ns"].unsqueeze(1)
    # Handle bars in the (level) box frame: EE distance to both bars.
    dx, dy = ee_x - box["nx"].unsqueeze(1), ee_y - box["ny"].unsqueeze(1)
    lx = torch.addcmul(ncu * dx, nsu, dy)
    ly = torch.addcmul(ncu * dy, nsu, dx, value=-1)
    lz = ee_z - (box["nz"] + st["box_hz"]).unsqueeze(1)
    ex = (ly.abs() - st["box_half_len"]).clamp(min=0.0)
    common = torch.addcmul(lz * lz, ex, ex)
    hx = st["box_hx"]
    dxp, dxm = lx - hx, lx + hx
    bar_p = torch.sqrt(torch.addcmul(common, dxp, dxp))
    bar_m = torch.sqrt(torch.addcmul(common, dxm, dxm))
    near_m = lx < 0  # handle 1 (-x) has the nearer centre
    grasp = grasp & (torch.where(st["handle"], bar_m, bar_p) < p.grasp_dist)
    # Closing axis against the bar axis: 1 - |cos(gripper yaw - box yaw)|.
    align = 1.0 - torch.addcmul(cg * ncu, sg, nsu).abs()
    f0 = st["finger"]
    fstep = p.finger_speed * p.dt
    f1 = torch.where(closed, (f0 - fstep).clamp(min=0.0), (f0 + fstep).clamp(max=FINGER_STROKE))
    new = (f0 > HANDLE_RADIUS) & (f1 <= HANDLE_RADIUS) & (torch.where(near_m, bar_m, bar_p) < p.grasp_dist)
    new = new & (align > p.grasp_align)
    return grasp, new, near_m, f1


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
    wx, wy, wzc, dr2 = wrist_in_reach(ex + EE_TO_WRIST[0], ey + EE_TO_WRIST[1], dz + EE_TO_WRIST[2])
    q_h = ik_wrist(wx, wy, wzc, dr2, torch.atan2(gs, gc) - yaw, zero)
    q6 = q[..., 5] + wrap_angle(q_h[..., 5] - q[..., 5])  # the same gripper yaw, nearest the current j6
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


def box_rotation(c: torch.Tensor, s: torch.Tensor, zero: torch.Tensor, one: torch.Tensor) -> torch.Tensor:
    return torch.stack([c, -s, zero, s, c, zero, zero, zero, one], -1).unflatten(-1, (3, 3))
