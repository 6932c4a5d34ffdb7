"""Two robots carrying one box on a low level (issue 67): where the legs are the limit.

The scripted pair (:class:`pnp.task.scripted.ScriptedPnP`, two robots) picks the box up by its
two handles and carries it to the goal; the same paired trials run on the ideal low level and on
the learned legs, so the differences are the legs'. Per episode, from the first step at which both
robots carry (scripted phase ``CARRY``) until the episode ends:

* ``falls``: the fall term fired (a trunk below its fall height);
* ``grasps_lost``: a robot's ``object_grabbed`` condition dropped while carrying (a handle slipped);
* ``ee_error``: distance of each EE from its command (base frame, clamped to the arm's reach)
  one HL step (0.1 s) after it was given;
* ``trunk_height``: the lowest trunk height seen;
* ``spacing_drift``: how far the distance between the two grippers moves from its value when the
  carry began (the paper's "robots resist each other": a pair that pulls apart or pushes together).
"""
from __future__ import annotations

from typing import Callable

import torch

from pnp.envs.pnp_env import PnPEnv
from pnp.sim.arm_ik import clamp_reach
from pnp.task import HL_DT, OBS_FIELDS
from pnp.task.terms import CONDITIONS, REWARD_TERMS
from pnp.task.scripted import CARRY, RELEASE, ScriptedPnP

_GRABBED, _FALL = CONDITIONS.index("object_grabbed"), REWARD_TERMS.index("fall")


def value_stats(x: torch.Tensor) -> dict:
    """Mean, 90th percentile, max and count of the finite entries of ``x``."""
    x = x[torch.isfinite(x)]
    if not len(x):
        return {"mean": None, "p90": None, "max": None, "samples": 0}
    return {"mean": float(x.mean()), "p90": float(torch.quantile(x, 0.9)), "max": float(x.max()), "samples": len(x)}


def dual_carry(make_env: Callable[[int], PnPEnv], episodes: int, max_steps: int) -> dict:
    """``episodes`` worlds of ``make_env(n)`` (two robots, paired trials), one episode each, driven by
    the scripted pair for at most ``max_steps`` HL steps; returns the carry measures (module docstring)."""
    env = make_env(episodes)
    if env.num_robots != 2:
        raise ValueError(f"dual_carry needs a two-robot env, got num_robots={env.num_robots}")
    try:
        script, td = ScriptedPnP(episodes, 2), env.reset()
        n = episodes
        live = torch.ones(n, dtype=torch.bool)  # episode not over
        carrying = torch.zeros(n, dtype=torch.bool)  # both robots have reached CARRY
        success, fell, lost = (torch.zeros(n, dtype=torch.bool) for _ in range(3))
        spacing0, drift = torch.full((n,), float("nan")), torch.zeros(n)
        trunk_min = torch.full((n,), float("inf"))
        errors, carry_steps = [], torch.zeros(n, dtype=torch.long)
        for _ in range(max_steps):
            td = script(td)
            command = clamp_reach(td.get(("agents", "action"))[..., 3:6])
            in_carry = live & ((script.phase >= CARRY) & (script.phase < RELEASE)).all(-1)
            out = env.step(td)
            nxt = out.get("next")
            ego = nxt.get(("agents", "ego"))[..., OBS_FIELDS["ego"]["ee_pos"]]
            ee = env.ee_positions()
            spacing = (ee[:, 0] - ee[:, 1]).norm(dim=-1)
            start = in_carry & ~carrying
            spacing0 = torch.where(start, spacing, spacing0)
            carrying |= in_carry
            if in_carry.any():
                errors.append((ego - command).norm(dim=-1)[in_carry].reshape(-1))
                drift = torch.where(in_carry, torch.maximum(drift, (spacing - spacing0).abs()), drift)
                trunk_min = torch.where(in_carry, torch.minimum(trunk_min, env.physical_state().base_z.min(-1)
                                                                .values), trunk_min)
                lost |= in_carry & ~nxt.get(("agents", "stage_conditions"))[..., _GRABBED].all(-1)
                carry_steps += in_carry.long()
            fell |= live & nxt.get(("agents", "reward_terms"))[..., _FALL].bool().any(-1)
            success |= live & nxt.get("success").squeeze(-1)
            live &= ~nxt.get("done").squeeze(-1)
            td = env.step_mdp(out)
            if not live.any():
                break
        c = carrying
        return {"episodes": n, "max_steps": max_steps, "carried": int(c.sum()), "success": int(success.sum()),
                "falls": int(fell.sum()), "falls_while_carrying": int((fell & c).sum()),
                "grasps_lost_while_carrying": int(lost.sum()),
                "carry_s_mean": float(carry_steps[c].float().mean() * HL_DT) if c.any() else None,
                "ee_error_m": value_stats(torch.cat(errors) if errors else torch.zeros(0)),
                "trunk_height_min_m": value_stats(trunk_min[c]), "spacing_drift_m": value_stats(drift[c])}
    finally:
        env.close()
