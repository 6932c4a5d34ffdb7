"""Render one episode offscreen on the CPU (MUJOCO_GL=egl, Debian's Mesa) to GIF or MP4.

    python recipes/render.py                                  # scripted policy, one robot
    python recipes/render.py --out results/scripted_pnp.gif --seed 3 --every 2
    python recipes/render.py --robots 2 --out results/scripted_dual_pnp.gif --every 3
    python recipes/render.py --checkpoint results/train_single/checkpoint_mujoco.pt --out results/single_pnp.gif
    python recipes/render.py --checkpoint <pnp run> --low-level-checkpoint runs/loco --out runs/walking.gif  # on legs

With ``--checkpoint`` the trained teacher acts with its deterministic (mean) action on the
MuJoCo backend (the robot count is the checkpoint's); up to ``--tries`` episodes (layouts
drawn in turn from ``--seed``) are rendered until one ends as ``--outcome`` asks (a success, or
a failure to show beside it), and the JSON says how many it took and whether one did.

Needs Debian's ``libegl1 libegl-mesa0 libgl1-mesa-dri`` (``make render-deps``).
"""
from __future__ import annotations

import argparse
import json
import os
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import imageio.v2 as imageio  # noqa: E402
import torch  # noqa: E402

from tensordict.nn import InteractionType, set_interaction_type  # noqa: E402


from pnp.envs.pnp_env import PnPEnv  # noqa: E402
from pnp.sim.render import WorldRenderer  # noqa: E402
from pnp.task.scripted import ScriptedPnP  # noqa: E402
from pnp.training.checkpoint import resolve_checkpoint  # noqa: E402
from pnp.training.provenance import provenance  # noqa: E402
from pnp.training.rollout import load_policy  # noqa: E402


def render_episode(env, policy, out: str, every: int = 2, width: int = 320, height: int = 240,
                   max_steps: int | None = None) -> dict:
    """Roll out world 0 of ``env`` (a PnPEnv, or a TransformedEnv around one) until its
    episode ends; write every ``every``-th frame."""
    base = getattr(env, "base_env", env)
    r = WorldRenderer(base.backend, 0, width=width, height=height)
    td = env.reset()
    frames, steps, success = [r.frame()], 0, False
    for steps in range(1, (max_steps or base.max_steps) + 1):
        td = env.step(policy(td))
        nxt = td["next"]
        if steps % every == 0:
            frames.append(r.frame())
        success = bool(nxt["success"][0])
        if bool(nxt["done"][0]):
            break
        td = env.step_mdp(td)
    frames.extend([frames[-1]] * 5)  # hold the last frame
    r.close()
    fps = 10 / every
    if out.endswith(".mp4"):
        imageio.mimsave(out, frames, fps=fps)
    else:
        imageio.mimsave(out, frames, duration=1000 / fps, loop=0)
    return {"steps": steps, "success": success, "frames": len(frames), "episode_s": steps * 0.1}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--robots", type=int, default=1)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--every", type=int, default=2, help="keep every n-th HL step (10 Hz)")
    p.add_argument("--out", default="results/scripted_pnp.gif")
    p.add_argument("--checkpoint", default=None, help="a trained teacher (run folder or .pt); default: scripted")
    p.add_argument("--tries", type=int, default=10, help="with --checkpoint: episodes tried until --outcome")
    p.add_argument("--outcome", choices=("success", "failure"), default="success",
                   help="with --checkpoint: the kind of episode to keep")
    p.add_argument("--max-steps", type=int, default=None, help="cut the episode short (default: 45 s)")
    p.add_argument("--low-level-checkpoint", default=None,
                   help="with --checkpoint: a task=locomotion run; the teacher acts on its walking legs")
    args = p.parse_args(argv)
    if args.robots not in (1, 2):
        raise SystemExit(f"--robots must be 1 or 2, got {args.robots}")
    t0 = time.time()
    if args.checkpoint:
        info = _render_teacher(args)
    else:
        torch.manual_seed(args.seed)
        env = PnPEnv(num_worlds=1, num_robots=args.robots, seed=args.seed)
        info = render_episode(env, ScriptedPnP(1, args.robots), args.out, every=args.every, max_steps=args.max_steps)
        info.update(provenance(seed=args.seed, policy="scripted"))
    info["wall_s"] = round(time.time() - t0, 1)
    with open(os.path.splitext(args.out)[0] + ".json", "w") as f:
        json.dump(info, f, indent=2)
    print(info)
    return info


def _render_teacher(args) -> dict:
    path = resolve_checkpoint(args.checkpoint, "runs")
    legs = {"low_level": "learned", "low_level_checkpoint": args.low_level_checkpoint} if args.low_level_checkpoint else {}
    # Not paired: a paired env's reset() restarts at trial 0, so every try would replay one layout.
    pol = load_policy(path, 1, args.seed, backend="mujoco", nthread=1, paired_trials=False, **legs)
    env, actor, ckpt, folded = pol.env, pol.actor, pol.ckpt, pol.folded
    want_success = args.outcome == "success"
    for k in range(args.tries):  # each reset draws the next layout from the env's seeded RNG
        with torch.no_grad(), set_interaction_type(InteractionType.DETERMINISTIC):
            info = render_episode(env, actor, args.out, every=args.every, max_steps=args.max_steps)
        if info["success"] == want_success:
            break
    env.close()
    info["outcome_wanted"], info["outcome_found"] = args.outcome, info["success"] == want_success
    info.update(provenance(seed=args.seed, policy=str(path), checkpoint_iteration=int(ckpt["counters"]["iteration"]),
                           episodes_tried=k + 1, folded_inputs=folded, low_level=str(pol.cfg.env.low_level),
                           low_level_checkpoint=args.low_level_checkpoint or pol.cfg.env.low_level_checkpoint))
    return info
