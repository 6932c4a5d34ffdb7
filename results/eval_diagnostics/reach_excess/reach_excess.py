import sys; sys.path.insert(0, "recipes")
import torch
from omegaconf import OmegaConf
from tensordict.nn import InteractionType, set_interaction_type
from evaluate import load_policy
from pnp.task import ACTION_HIGH, ACTION_LOW, ee_out_of_reach
ev = OmegaConf.create({"backend": None, "nthread": 2, "max_episode_steps": None, "start_range": None})
env, actor, *_ = load_policy(sys.argv[1], ev, 64, 5)
td = env.reset(); ex = {s: [] for s in range(7)}
mode = InteractionType.RANDOM if len(sys.argv) > 2 else InteractionType.DETERMINISTIC
with torch.no_grad(), set_interaction_type(mode):
    for t in range(300):
        td = actor(td)
        a = td["agents", "action"].clamp(torch.tensor(ACTION_LOW), torch.tensor(ACTION_HIGH))  # as the env clips
        e = ee_out_of_reach(a[..., 3:6]).view(-1); st = td["agents", "stage"].view(-1)
        for s in range(7): ex[s].append(e[st == s])
        _, td = env.step_and_maybe_reset(td)
for s in range(7):
    e = torch.cat(ex[s])
    if len(e): print(s, len(e), "frac>0 %.2f mean %.3f p90 %.3f" % ((e > 0).float().mean(), e.mean(), e.quantile(0.9)))
