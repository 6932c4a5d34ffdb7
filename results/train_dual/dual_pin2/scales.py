"""Policy loc and scale (pre-tanh) of dual checkpoints over 150 sampled steps, 128 worlds, seed 7.

    python results/train_dual/dual_pin2/scales.py OUT.json CHECKPOINT...
"""
import json, platform, subprocess, sys, time, torch
sys.path.insert(0, "recipes")
from omegaconf import OmegaConf
from tensordict.nn import InteractionType, set_interaction_type
import _common
from _warm_start import load_module
out = {"rows": [], "command": "python " + " ".join(sys.argv), "seed": 7, "worlds": 128, "steps": 150,
       "commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip(),
       "machine": f"{platform.system()} {platform.machine()}, 2 cores"}
t0 = time.monotonic()
for path in sys.argv[2:]:
    ck = _common.load_checkpoint(path); W = 128
    cfg = OmegaConf.create(ck["cfg"]); cfg.env.num_worlds = W; cfg.env.max_episode_steps = 305
    env = _common.make_env(cfg.env, cfg.curriculum, 7)
    actor, *_ = _common.make_models(cfg.model, env, "popart", 0.98)
    load_module(actor, ck["actor"])
    locs, scales = [], []
    with torch.no_grad(), set_interaction_type(InteractionType.RANDOM):
        td = env.reset()
        for t in range(150):
            td = actor(td); locs.append(td["agents", "loc"].clone()); scales.append(td["agents", "scale"].clone())
            td = env.step_mdp(env.step(td))
    L = torch.stack(locs); S = torch.stack(scales)
    out["rows"].append({"checkpoint": path, "iteration": ck["counters"]["iteration"],
                        "loc_abs_mean": L.abs().mean((0, 1, 2)).tolist(), "share_loc_abs_gt_2": (L.abs() > 2).float().mean((0, 1, 2)).tolist(),
                        "scale_mean": S.mean((0, 1, 2)).tolist()})
    print(path, ck["counters"]["iteration"])
    print("  |loc| mean", [round(x, 2) for x in L.abs().mean((0, 1, 2)).tolist()])
    print("  share |loc|>2", [round(x, 2) for x in (L.abs() > 2).float().mean((0, 1, 2)).tolist()])
    print("  scale mean", [round(x, 3) for x in S.mean((0, 1, 2)).tolist()])
out["wall_s"] = round(time.monotonic() - t0, 1)
json.dump(out, open(sys.argv[1], "w"), indent=1)
