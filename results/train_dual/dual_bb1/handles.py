"""Two robots on one box: do they grasp together, and at which handle? Roll-out of a dual
checkpoint on its own (kinematic) env, 128 worlds, 300 steps, seed 7.

    python results/train_dual/dual_bb1/handles.py CHECKPOINT det|rand OUT.json [env.KEY=VALUE ...]
"""
import json, platform, subprocess, sys, time, torch
sys.path.insert(0, "recipes")
from omegaconf import OmegaConf
from tensordict.nn import InteractionType, set_interaction_type
import _common
from _warm_start import load_module
from pnp.task import handles

t0 = time.monotonic()
ck = _common.load_checkpoint(sys.argv[1]); mode = sys.argv[2]; W, steps = 128, 300
cfg = OmegaConf.create(ck["cfg"]); cfg.env.num_worlds = W; cfg.env.max_episode_steps = steps + 5
cfg = OmegaConf.merge(cfg, OmegaConf.from_dotlist(sys.argv[4:]))  # e.g. env.handle_order=own_last
env = _common.make_env(cfg.env, cfg.curriculum, 7)
actor, *_ = _common.make_models(cfg.model, env, "popart", 0.98)
load_module(actor, ck["actor"])
grasped_ever = torch.zeros(W, 2, dtype=torch.bool); both_ever = torch.zeros(W, dtype=torch.bool)
lifted = torch.zeros(W, dtype=torch.bool); ready_ever = torch.zeros(W, 2, dtype=torch.bool); ready_both = lifted.clone(); same = torch.zeros(W); both_close = torch.zeros(W); grasp_steps = torch.zeros(W, 2)
with torch.no_grad(), set_interaction_type(InteractionType.DETERMINISTIC if mode == "det" else InteractionType.RANDOM):
    td = env.reset()
    for t in range(steps):
        td = env.step(actor(td)); n = td["next"]
        c = n["agents", "stage_conditions"]; g = c[..., 1]
        ready_ever |= c[..., 0]; ready_both |= c[..., 0].all(-1);
        grasped_ever |= g; both_ever |= g.all(-1); lifted |= c[..., 2].any(-1); grasp_steps += g
        # World-frame handles (the object block's order depends on env.handle_order).
        base = env.base_env
        s = base.backend.state(base._goal, base._init_goal_dist, torch.zeros(W, 2))
        d = (handles(s)[:, None] - s.ee_pos[:, :, None]).norm(dim=-1)  # [N, R, 2]
        near1 = d[..., 1] < d[..., 0]
        same += (near1[:, 0] == near1[:, 1]).float()
        both_close += (d.min(-1).values < 0.15).all(-1).float()
        td = env.step_mdp(td)
out = {"checkpoint": sys.argv[1], "iteration": ck["counters"]["iteration"], "mode": mode, "worlds": W, "steps": steps, "seed": 7,
       "robot_ready_ever": ready_ever.float().mean().item(), "world_both_ready_at_once": ready_both.float().mean().item(),
       "world_both_ready_at_some_time": ready_ever.all(-1).float().mean().item(), "robot_grasped_ever": grasped_ever.float().mean().item(), "world_both_grasped_at_once": both_ever.float().mean().item(),
       "world_both_grasped_at_some_time": grasped_ever.all(-1).float().mean().item(), "world_lifted": lifted.float().mean().item(),
       "grasp_steps_per_robot": grasp_steps.mean().item(), "share_of_steps_nearest_handle_same": (same / steps).mean().item(),
       "steps_both_within_15cm_of_a_handle": both_close.mean().item(),
       "command": "python " + " ".join(sys.argv),
       "commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip(),
       "machine": f"{platform.system()} {platform.machine()}, 2 cores", "wall_s": round(time.monotonic() - t0, 1)}
json.dump(out, open(sys.argv[3], "w"), indent=1)
print(out)
