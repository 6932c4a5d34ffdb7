"""How well a low level does what the high level asks (issue 24): velocity tracking, EE
tracking, falls under pushes while carrying, and how often the leg servos saturate.

A leg policy is any callable ``observations [M, LOCO_OBS_DIM] -> actions [M, 12]``
(:func:`pnp.training.low_level.load_locomotion_policy`). Velocity tracking and pushes run
in :class:`pnp.envs.locomotion_env.LocomotionEnv` (the leg policy's own task, its payload a
constant downward force at the gripper standing in for a carried box); EE tracking runs in
the pick-and-place backends, ideal and learned side by side, on the same commands.
"""
from __future__ import annotations

from types import SimpleNamespace
from typing import Callable

import numpy as np
import torch

from pnp.sim.backend import Layout, MujocoBackend
from pnp.sim.box import SINGLE_ROBOT_BOXES
from pnp.envs.locomotion_env import SETTINGS
from pnp.sim.arm_ik import clamp_reach
from pnp.legs.locomotion import LOCO_OBS_FIELDS, POLICY_DT, STAND, LegServo
from pnp.sim.robot import LEG_TORQUE, leg_ranges
from pnp.task import ACTION_HIGH, ACTION_LOW, HL_DT, yaw_rotation

LegPolicy = Callable[[torch.Tensor], torch.Tensor]
TORQUE_SATURATED = 0.99  # share of the torque limit counted as saturated
LIMIT_MARGIN = 0.02  # rad from a joint's range end counted as at its limit
_LO, _HI = (torch.tensor(leg_ranges()[:, i], dtype=torch.float32) for i in (0, 1))


class Saturation:
    """Counts leg joint-steps at the torque limit (the servo PD at the policy step's start) and at a range end."""

    def __init__(self, servo: LegServo):
        self.servo, self.torque, self.limit, self.total = servo, 0, 0, 0

    def add(self, action: torch.Tensor, q: torch.Tensor, qd: torch.Tensor, live: torch.Tensor) -> None:
        """Leg ``action`` [N, 12] just applied from state ``q``, ``qd`` [N, 12]; only ``live`` [N] worlds count."""
        tau = self.servo.torques(self.servo.targets(action), q, qd)[live]
        q = q[live]
        self.torque += int((tau.abs() >= TORQUE_SATURATED * LEG_TORQUE).sum())
        self.limit += int(((q <= _LO + LIMIT_MARGIN) | (q >= _HI - LIMIT_MARGIN)).sum())
        self.total += tau.numel()

    def rates(self) -> dict:
        n = max(self.total, 1)
        return {"torque_saturation_rate": self.torque / n, "joint_limit_rate": self.limit / n, "joint_steps": self.total}


def _act(env, policy: LegPolicy, td):
    """One policy step of ``env``; returns (step tensordict, leg action [N, 12], leg q and qd
    [N, 12] the step started from, read off the observation the policy acted on)."""
    obs = td.get(("agents", "observation"))[:, 0]
    action = policy(obs).clamp(-1.0, 1.0)
    out = env.step(td.set(("agents", "action"), action.unsqueeze(1)))
    return out, action, obs[:, LOCO_OBS_FIELDS["leg_q"]] + STAND, obs[:, LOCO_OBS_FIELDS["leg_qd"]]


def velocity_tracking(make_env, policy: LegPolicy, commands, repeats: int = 4, settle_s: float = 2.0,
                      measure_s: float = 4.0) -> dict:
    """Each command [K, 3] (vx, vy m/s, yaw rate rad/s) held in ``repeats`` worlds: after
    ``settle_s`` the base-frame velocity error is averaged over ``measure_s``. ``make_env(n)``
    returns a LocomotionEnv of n worlds without pushes or command resampling."""
    commands = torch.as_tensor(commands, dtype=torch.float32)
    k = len(commands)
    env = make_env(k * repeats)
    try:
        cmd = commands.repeat_interleave(repeats, 0)
        td = env.reset()
        env.set_command(cmd)
        fell = torch.zeros(env.num_worlds, dtype=torch.bool)
        lin_err = torch.zeros(env.num_worlds)
        yaw_err = torch.zeros(env.num_worlds)
        settle, measure = round(settle_s / POLICY_DT), round(measure_s / POLICY_DT)
        sat = Saturation(env.servo)
        for t in range(settle + measure):
            out, action, q, qd = _act(env, policy, td)
            fell |= out.get(("next", "terminated"))[:, 0]
            sat.add(action, q, qd, ~fell)
            if t >= settle:
                nxt = out.get(("next", "agents", "observation"))[:, 0]
                lin_err += (nxt[:, LOCO_OBS_FIELDS["base_lin_vel"]][:, :2] - cmd[:, :2]).norm(dim=-1)
                yaw_err += (nxt[:, LOCO_OBS_FIELDS["base_ang_vel"]][:, 2] - cmd[:, 2]).abs()
            td = out.get("next")
            if out.get(("next", "truncated")).any():
                raise RuntimeError("an episode was truncated during velocity tracking: raise max_episode_steps")
        # A fallen trunk's error is not tracking: it counts as a fall instead.
        lin_err, yaw_err = lin_err / measure, yaw_err / measure
        rows = []
        for i, c in enumerate(commands.tolist()):
            w = slice(i * repeats, (i + 1) * repeats)
            up = ~fell[w]
            rows.append({"command": c, "falls": int(fell[w].sum()),
                         "lin_vel_error": float(lin_err[w][up].mean()) if up.any() else None,
                         "yaw_rate_error": float(yaw_err[w][up].mean()) if up.any() else None})
        up = ~fell
        return {"per_command": rows, "repeats": repeats, "settle_s": settle_s, "measure_s": measure_s,
                "lin_vel_error_mean": float(lin_err[up].mean()) if up.any() else None,
                "yaw_rate_error_mean": float(yaw_err[up].mean()) if up.any() else None,
                "fall_rate": float(fell.float().mean()), **sat.rates()}
    finally:
        env.close()


def push_recovery(make_env, policy: LegPolicy, episodes: int, seconds: float) -> dict:
    """``episodes`` worlds of ``make_env(n)`` (pushes and payloads as configured there, random
    commands) for ``seconds``; a world that falls stays counted and is not run further."""
    env = make_env(episodes)
    try:
        td = env.reset()
        fell = torch.zeros(episodes, dtype=torch.bool)
        pushes = torch.zeros(episodes, dtype=torch.long)
        sat = Saturation(env.servo)
        for _ in range(round(seconds / POLICY_DT)):
            before = env._push_in.clone()
            out, action, q, qd = _act(env, policy, td)
            pushed = env._push_in > before  # the countdown was reset: a kick was given
            pushes += (pushed & ~fell).long()
            fell |= out.get(("next", "terminated"))[:, 0]
            sat.add(action, q, qd, ~fell)
            if out.get(("next", "truncated")).any():
                raise RuntimeError("an episode was truncated during the push test: raise max_episode_steps")
            td = out.get("next")
        return {"episodes": episodes, "seconds": seconds, "pushes": int(pushes.sum()), "falls": int(fell.sum()),
                "fall_rate": float(fell.float().mean()), "falls_per_push": float(fell.sum() / max(int(pushes.sum()), 1)),
                "payload_kg": list(env.payload_mass), "push_speed": list(env.push_speed),
                "push_interval_s": env.push_steps * POLICY_DT, **sat.rates()}
    finally:
        env.close()


def locomotion_settings(base, **changes) -> SimpleNamespace:
    """Locomotion settings ``base`` (``LocomotionConfig`` or the ``env.locomotion`` node of a
    checkpoint's config) with ``changes``."""
    unknown = set(changes) - set(SETTINGS)
    if unknown:
        raise ValueError(f"unknown locomotion settings {sorted(unknown)}; known: {list(SETTINGS)}")
    return SimpleNamespace(**{**{k: getattr(base, k) for k in SETTINGS}, **changes})


def ee_tracking(backend: MujocoBackend, switches: int, delays_s=(0.1, 0.3, 1.0), hold_s: float = 1.0,
                base_command=(0.0, 0.0, 0.0), seed: int = 0, *, fall_height: float) -> dict:
    """EE position error after each of ``delays_s`` since the EE command jumped to a new random
    pose of the HL action's box, ``switches`` times per world, with the base commanded at
    ``base_command``. The target is the command in the level trunk frame (trunk position and
    yaw, no pitch or roll), where the high level's EE command lives: a trunk that pitches or
    rolls counts against the low level; its height is reported beside (``trunk_height_*``).
    A world whose trunk has been below ``fall_height`` counts as a fall, and its errors from
    then on are left out, as in :func:`velocity_tracking`. One robot; the box far away."""
    g = torch.Generator().manual_seed(seed)
    n = backend.num_worlds
    box = SINGLE_ROBOT_BOXES[0]
    backend.reset(torch.arange(n), Layout(
        base=torch.zeros(n, 1, 3), box_xy_yaw=torch.tensor([50.0, 0.0, 0.0]).expand(n, 3).clone(),
        box_size=torch.tensor(box.size).expand(n, 3).clone(), box_mass=torch.full((n,), box.mass)))
    lo, hi = torch.tensor(ACTION_LOW[3:7]), torch.tensor(ACTION_HIGH[3:7])
    delays = [round(d / HL_DT) for d in delays_s]
    hold = max(round(hold_s / HL_DT), max(delays))
    action = torch.zeros(n, 1, 8)
    action[..., :3] = torch.tensor(base_command, dtype=torch.float32)
    errors = {d: [] for d in delays_s}
    heights = []
    fell = torch.zeros(n, dtype=torch.bool)
    for switch in range(switches + 1):  # the first hold only settles
        ee = lo + (hi - lo) * torch.rand(n, 4, generator=g)
        action[:, 0, 3:7] = ee
        for t in range(1, hold + 1):
            if backend.step(action).any():
                raise RuntimeError("physics diverged during the EE tracking test")
            if switch and t in delays:
                s = backend.state(torch.zeros(n, 2), torch.ones(n), torch.zeros(n, 1))
                base = s.base[:, 0]
                origin = torch.cat([base[:, :2], s.base_z], -1)
                target = origin + (yaw_rotation(base[:, 2]) @ clamp_reach(ee[:, :3]).unsqueeze(-1)).squeeze(-1)
                fell |= s.base_z[:, 0] < fall_height
                errors[delays_s[delays.index(t)]].append((s.ee_pos[:, 0] - target).norm(dim=-1)[~fell])
                heights.append(s.base_z[~fell, 0])
    out = {}
    for d, e in errors.items():
        e = torch.cat(e)
        out[f"{d:g}s"] = {"mean_m": float(e.mean()) if len(e) else None, "median_m": float(e.median()) if len(e) else None,
                          "p90_m": float(torch.quantile(e, 0.9)) if len(e) else None, "samples": len(e)}
    heights = torch.cat(heights)
    return {"after": out, "switches": switches, "worlds": n, "hold_s": hold * HL_DT, "base_command": list(base_command),
            "falls": int(fell.sum()), "fall_height_m": fall_height,
            "trunk_height_mean_m": float(heights.mean()) if len(heights) else None,
            "trunk_height_std_m": float(heights.std()) if len(heights) > 1 else None}


def command_grid(low, high, steps: int = 3) -> list[list[float]]:
    """vx x yaw-rate grid (vy 0) plus pure vy commands, each from ``low`` to ``high`` in ``steps``."""
    vx = np.linspace(low[0], high[0], steps)
    wz = np.linspace(low[2], high[2], steps)
    grid = [[float(x), 0.0, float(w)] for x in vx for w in wz]
    grid += [[0.0, float(y), 0.0] for y in np.linspace(low[1], high[1], steps) if abs(y) > 1e-9]
    return grid

