"""Which handle does the one-robot dual-box policy go to, and how do handle claims and
handle orders change that? Sampled actions, 128 worlds, 300 steps, seed 7, kinematic.

    python results/train_dual/bigbox2r/handle_habit.py CHECKPOINT OUT.json
"""
import json, platform, subprocess, sys, time, torch
sys.path.insert(0, "recipes")
from omegaconf import OmegaConf
from tensordict.nn import InteractionType, set_interaction_type
import _common
from _warm_start import load_module
import pnp.task as T

t0 = time.monotonic()
ck = _common.load_checkpoint(sys.argv[1]); W, steps = 128, 300


def run(order: str, claim: bool) -> dict:
    cfg = OmegaConf.create(ck["cfg"]); cfg.env.num_worlds = W; cfg.env.max_episode_steps = steps + 5
    cfg.env.handle_order, cfg.env.handle_claim = order, claim
    env = _common.make_env(cfg.env, cfg.curriculum, 7)
    actor, *_ = _common.make_models(cfg.model, env, "popart", 0.98)
    load_module(actor, ck["actor"])
    b = env.base_env

    def nearest():  # the handle nearest the EE, claims aside
        return T.geometry(b.backend.state(b._goal, b._init_goal_dist, torch.zeros(W, 1))).own[:, 0].clone()

    first = torch.full((W,), -1); flips = 0; ready = torch.zeros(W, dtype=torch.bool)
    with torch.no_grad(), set_interaction_type(InteractionType.RANDOM):
        td = env.reset(); at_reset = prev = nearest()
        for _ in range(steps):
            td = env.step(actor(td)); r = td["next", "agents", "stage_conditions"][:, 0, 0]
            now = nearest(); flips += int((now != prev).sum()); prev = now
            first = torch.where((first < 0) & r, now.long(), first); ready |= r
            td = env.step_mdp(td)
    ok = first >= 0
    return {"handle_order": order, "handle_claim": claim, "ready_share": ready.float().mean().item(),
            "first_ready_at_handle_1": (first[ok] == 1).float().mean().item() if ok.any() else None,
            "first_ready_at_reset_nearest": (first[ok] == at_reset[ok].long()).float().mean().item() if ok.any() else None,
            "nearest_handle_flips": flips, "robot_steps": W * steps}


rows = [run(o, c) for o, c in (("identity", False), ("identity", True), ("own_first", True), ("own_last", True))]
out = {"checkpoint": sys.argv[1], "iteration": ck["counters"]["iteration"], "rows": rows, "worlds": W, "steps": steps,
       "seed": 7, "command": "python " + " ".join(sys.argv),
       "commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip(),
       "machine": f"{platform.system()} {platform.machine()}, 2 cores", "wall_s": round(time.monotonic() - t0, 1)}
json.dump(out, open(sys.argv[2], "w"), indent=1)
print(json.dumps(rows, indent=1))
