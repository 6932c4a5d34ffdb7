"""Deterministic roll-out of a dual checkpoint on the kinematic backend, 256 worlds (seed 7):
collisions, "gripper ready" and grasp shares, closest EE-handle distance.

    python results/train_dual/dual_floor1/dualdiag.py CHECKPOINT ROBOTS STEPS BOXES BLOCKS OUT.json
"""
import json, platform, subprocess, sys, torch
sys.path.insert(0, "recipes")
from omegaconf import OmegaConf
from tensordict.nn import InteractionType, set_interaction_type
import _common
from _warm_start import load_module
from pnp.terms import REWARD_TERMS, CONDITIONS
ck = _common.load_checkpoint(sys.argv[1]); robots = int(sys.argv[2]); steps = int(sys.argv[3])
cfg = OmegaConf.create(ck["cfg"]); cfg.env.boxes = (sys.argv[4] if len(sys.argv) > 4 else cfg.env.get("boxes")); cfg.env.num_robots = robots; cfg.env.box_blocks_base = len(sys.argv) > 5; cfg.env.num_worlds = 256; cfg.env.max_episode_steps = steps + 5
env = _common.make_env(cfg.env, cfg.curriculum, 7)
actor, critic, *_ = _common.make_models(cfg.model, env, "popart", 0.98)
load_module(actor, ck["actor"])
net = actor.module[0].module
folded = _common.fold_constant_inputs(net.obs_norm, [net])
COL = REWARD_TERMS.index("collision")
td = env.reset()
col = torch.zeros(256, robots); ready = torch.zeros(256, robots, dtype=torch.bool); grab = ready.clone()
mind = torch.full((256, robots), 9.0)
with torch.no_grad(), set_interaction_type(InteractionType.DETERMINISTIC):
    for t in range(steps):
        td = actor(td); td = env.step(td); n = td["next"]
        col += n["agents", "reward_terms"][..., COL]
        c = n["agents", "stage_conditions"]; ready |= c[..., 0]; grab |= c[..., 1]
        obj = n["agents", "object"]  # handle - ee at 15:18, 18:21 (base frame)
        d = torch.minimum(obj[..., 15:18].norm(dim=-1), obj[..., 18:21].norm(dim=-1))
        mind = torch.minimum(mind, d)
        td = env.step_mdp(td)
q = mind.flatten().quantile(torch.tensor([0.1, 0.5, 0.9])).tolist()
out = {"checkpoint": sys.argv[1], "iteration": ck["counters"]["iteration"], "robots": robots, "steps": steps, "boxes": sys.argv[4],
       "box_blocks_base": cfg.env.box_blocks_base, "worlds": 256, "seed": 7, "folded_inputs": folded,
       "collision_steps_per_robot": col.mean().item(), "ready_share": ready.float().mean().item(),
       "grab_share": grab.float().mean().item(), "min_ee_handle_m_q10_50_90": q,
       "command": "python " + " ".join(sys.argv),
       "commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip(),
       "machine": f"{platform.system()} {platform.machine()}, 2 cores"}
json.dump(out, open(sys.argv[6], "w"), indent=1)
print(out)
