"""How grasps end under a checkpoint's *stochastic* policy: opened by the policy, or lost
with the gripper still closed (drift off the bar, out of reach).

    python recipes/analyze/grasp_losses.py checkpoint=results/train_dual/dual_bb1/checkpoint.pt \
        out=runs/grasp_losses.json env.handle_order=own_last env.handle_claim=true

Counts, over ``worlds`` worlds and ``steps`` steps (actions sampled, seeded): grasps that
ended with the gripper opened or closed, grasp-steps kept, the share of worlds where every
robot held its handle at once or the box was lifted, and the median EE step while held.
"""
from __future__ import annotations

import time

import torch
from omegaconf import OmegaConf
from tensordict.nn import InteractionType, set_interaction_type

from pnp.task.terms import CONDITIONS
from pnp.training.rollout import load_policy

from pnp.analysis.analysis_cli import save, settings

GRABBED, LIFTED = CONDITIONS.index("object_grabbed"), CONDITIONS.index("object_lifted")
DEFAULTS = {"checkpoint": None, "out": "runs/grasp_losses.json", "worlds": 128, "steps": 300, "seed": 7, "env": {}}


def grasp_losses(checkpoint: str, worlds: int, steps: int, seed: int, **env) -> dict:
    pol = load_policy(checkpoint, worlds, seed, max_episode_steps=steps + 5, **env)
    torch.manual_seed(seed)  # the sampled actions
    base, t0 = pol.env.base_env, time.monotonic()
    opened = lost_closed = kept = 0
    both = torch.zeros(worlds, dtype=torch.bool)
    lifted, prev, ee_steps = both.clone(), None, []
    with torch.no_grad(), set_interaction_type(InteractionType.RANDOM):
        td = pol.env.reset()
        for _ in range(steps):
            ee0 = base.ee_positions()
            td = pol.env.step(pol.actor(td))
            cond = td["next", "agents", "stage_conditions"]
            held, shut = cond[..., GRABBED], td["agents", "action"][..., 7] > 0.5
            if prev is not None:
                ee_steps.append((base.ee_positions() - ee0).norm(dim=-1)[prev & shut])
                lost = prev & ~held
                opened += int((lost & ~shut).sum())
                lost_closed += int((lost & shut).sum())
                kept += int((prev & held).sum())
            prev, both, lifted = held.clone(), both | held.all(-1), lifted | cond[..., LIFTED].any(-1)
            td = pol.env.step_mdp(td)
    pol.env.close()
    steps_held = torch.cat(ee_steps) if ee_steps else torch.zeros(0)
    return {"checkpoint": str(checkpoint), "iteration": int(pol.ckpt["counters"]["iteration"]), "env": env,
            "worlds": worlds, "steps": steps, "seed": seed, "grasps_ended_opened": opened,
            "grasps_lost_closed": lost_closed, "grasp_steps_kept": kept,
            "world_both_grasped_at_once": float(both.float().mean()), "world_lifted": float(lifted.float().mean()),
            "ee_step_m_while_held_median": float(steps_held.median()) if len(steps_held) else None,
            "wall_s": time.monotonic() - t0}


def main(argv: list[str]) -> dict:
    cfg = settings(argv, DEFAULTS, __doc__)
    out = grasp_losses(cfg.checkpoint, int(cfg.worlds), int(cfg.steps), int(cfg.seed),
                       **OmegaConf.to_container(cfg.env))
    save(out, cfg.out)
    print(out)
    return out
