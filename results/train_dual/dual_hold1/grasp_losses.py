"""How grasps end under a dual checkpoint's stochastic policy: opened, or lost with the
gripper still closed (drift off the bar, reach). 128 worlds, 300 steps, seed 7.

    python results/train_dual/dual_hold1/grasp_losses.py CHECKPOINT OUT.json [env.KEY=VALUE ...]
"""
import json, platform, subprocess, sys, time, torch
sys.path.insert(0, "recipes")
from omegaconf import OmegaConf
from tensordict.nn import InteractionType, set_interaction_type
import _common
from _warm_start import load_module

t0 = time.monotonic(); torch.manual_seed(7)  # the sampled actions
ck = _common.load_checkpoint(sys.argv[1]); W, steps = 128, 300
cfg = OmegaConf.create(ck["cfg"]); cfg.env.num_worlds = W; cfg.env.max_episode_steps = steps + 5
cfg = OmegaConf.merge(cfg, OmegaConf.from_dotlist(sys.argv[3:]))
env = _common.make_env(cfg.env, cfg.curriculum, 7)
actor, *_ = _common.make_models(cfg.model, env, "popart", 0.98)
load_module(actor, ck["actor"])
opened = closed_lost = kept = 0; both = torch.zeros(W, dtype=torch.bool); lifted = both.clone(); prev = None
base = env.base_env; ee_steps = []  # EE displacement per step of robots grasped at its start, command closed
ee = lambda: base.backend.state(base._goal, base._init_goal_dist, torch.zeros(W, 2)).ee_pos.clone()  # noqa: E731
with torch.no_grad(), set_interaction_type(InteractionType.RANDOM):
    td = env.reset()
    for t in range(steps):
        ee0 = ee()
        td = env.step(actor(td)); c = td["next", "agents", "stage_conditions"]; g = c[..., 1]  # grasped
        shut = td["agents", "action"][..., 7] > 0.5
        if prev is not None:
            ee_steps.append((ee() - ee0).norm(dim=-1)[prev & shut])
        if prev is not None:
            lost = prev & ~g
            opened += int((lost & ~shut).sum()); closed_lost += int((lost & shut).sum()); kept += int((prev & g).sum())
        prev = g.clone(); both |= g.all(-1); lifted |= c[..., 2].any(-1)
        td = env.step_mdp(td)
out = {"checkpoint": sys.argv[1], "iteration": ck["counters"]["iteration"], "overrides": sys.argv[3:], "worlds": W, "steps": steps,
       "seed": 7, "grasps_ended_opened": opened, "grasps_lost_closed": closed_lost, "grasp_steps_kept": kept,
       "world_both_grasped_at_once": both.float().mean().item(),
       "ee_step_m_while_held_median": torch.cat(ee_steps).median().item(), "world_lifted": lifted.float().mean().item(),
       "command": "python " + " ".join(sys.argv),
       "commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip(),
       "machine": f"{platform.system()} {platform.machine()}, 2 cores", "wall_s": round(time.monotonic() - t0, 1)}
json.dump(out, open(sys.argv[2], "w"), indent=1)
print(out)
