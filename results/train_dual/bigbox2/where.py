"""Where one robot ends up on the dual boxes: deterministic policy, kinematic backend,
base blocked by the box, 256 worlds (seed 7), 120 steps (12 s).

    python results/train_dual/bigbox2/where.py CHECKPOINT dual OUT.json
"""
import json, platform, subprocess, sys, time, torch
sys.path.insert(0, "recipes")
from omegaconf import OmegaConf
from tensordict.nn import InteractionType, set_interaction_type
import _common
from _warm_start import load_module
from pnp.task import geometry
t0 = time.time()
ck = _common.load_checkpoint(sys.argv[1]); boxes = sys.argv[2]; N = 256
cfg = OmegaConf.create(ck["cfg"]); cfg.env.boxes = boxes; cfg.env.num_robots = 1; cfg.env.box_blocks_base = True
cfg.env.num_worlds = N; cfg.env.max_episode_steps = 200; cfg.env.backend = "kinematic"; cfg.env.nthread = 1
env = _common.make_env(cfg.env, cfg.curriculum, 7)
actor, critic, *_ = _common.make_models(cfg.model, env, "popart", 0.98)
load_module(actor, ck["actor"])
base = env.base_env
td = env.reset(); ready = torch.zeros(N, dtype=torch.bool)
with torch.no_grad(), set_interaction_type(InteractionType.DETERMINISTIC):
    for t in range(120):
        td = actor(td); a = td["agents", "action"]; td = env.step(td)
        ready |= td["next", "agents", "stage_conditions"][:, 0, 0]
        td = env.step_mdp(td)
s = base.backend.state(base._goal, base._init_goal_dist, (a[..., 7] > 0.5).float())
g = geometry(s)
R = s.box_rot[:, :2, :2]  # world xy of box x,y axes in columns
rel = s.base[:, 0, :2] - s.box_pos[:, :2]
bx = (R.transpose(1, 2) @ rel.unsqueeze(-1)).squeeze(-1)  # base in box frame
ha = s.box_size[:, 0] / 2; hb = s.box_size[:, 1] / 2
exy = torch.hypot(g.ee_handle[:, 0, 0], g.ee_handle[:, 0, 1])
bh = torch.hypot(g.handle[:, 0, 0] - s.base[:, 0, 0], g.handle[:, 0, 1] - s.base[:, 0, 1])
cmd = a[:, 0, 3:6]
print("ready", ready.float().mean().item())
print("frac base beyond box end |x|>a/2:", (bx[:, 0].abs() > ha).float().mean().item(), " beside (|y|>b/2 & |x|<a/2):", ((bx[:, 1].abs() > hb) & (bx[:, 0].abs() < ha)).float().mean().item())
q = torch.tensor([0.1, 0.5, 0.9])
print("EE-handle xy quantiles", exy.quantile(q).tolist())
print("base-handle xy quantiles", bh.quantile(q).tolist())
print("EE cmd x quantiles", cmd[:, 0].quantile(q).tolist())
out = {"checkpoint": sys.argv[1], "iteration": ck["counters"]["iteration"], "boxes": boxes, "worlds": N, "steps": 120, "seed": 7,
       "ready_share": ready.float().mean().item(),
       "base_beyond_box_end_share": (bx[:, 0].abs() > ha).float().mean().item(),
       "ee_handle_xy_m_q10_50_90": exy.quantile(q).tolist(), "base_handle_xy_m_q10_50_90": bh.quantile(q).tolist(),
       "ee_cmd_x_m_q10_50_90": cmd[:, 0].quantile(q).tolist(),
       "command": "python " + " ".join(sys.argv),
       "commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip(),
       "machine": f"{platform.system()} {platform.machine()}, 2 cores", "wall_s": time.time() - t0}
json.dump(out, open(sys.argv[3], "w"), indent=1)
