"""Where a training iteration's time goes: policy forward, env step (physics + task terms +
TorchRL transforms) and the PPO update, for any training configuration.

    python recipes/analyze/profile_iteration.py experiment=single_pnp_pipeline iterations=3 out=runs/profile.json
    python recipes/analyze/profile_iteration.py backend=mujoco env.num_worlds=1024 collect.frames_per_batch=16384
    python recipes/analyze/profile_iteration.py resume=runs/main/5_mujoco/checkpoint.pt threads=1/2

Arguments are those of recipes/train.py (hydra overrides) plus ``iterations`` (timed after
one untimed warm-up iteration), ``out`` and ``threads``: torch's thread counts for collection
and update, as pairs, e.g. ``threads=1/1,1/2,2/2``; each pair is profiled in turn in this
process and reported with its ratio to the first. MuJoCo's pool runs on ``env.nthread``.
On MuJoCo the physics of each timed iteration is replayed through raw ``mujoco.rollout``
(same models, states and controls) right after it: ``ratio_to_raw_physics`` is raw seconds
over iteration seconds (1.0: training costs what its physics costs, and nothing more).
With ``resume=<checkpoint>`` the run's own settings, weights and worlds are profiled where it
stopped (nothing is written to its folder): a trained policy's grasps and carries cost MuJoCo
~2x the contacts of a fresh policy's first steps, so only that measures a phase as it trains.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from tensordict.nn import InteractionType, set_interaction_type

from pnp.analysis.benchmark_env import record_physics, replay_raw
from pnp.training.checkpoint import restore_training_state
from pnp.training.choices import RECIPES_CONFIG
from pnp.training.config import register
from pnp.training.device import policy_step, training_device
from pnp.training.ppo import ppo_update
from pnp.training.provenance import provenance
from pnp.training.trainer import make_training, resume_config



def profile(cfg, iterations: int, collect_threads: int = 1, update_threads: int = 1, ckpt: dict | None = None) -> dict:
    torch.manual_seed(int(cfg.seed))
    env, models, loss = make_training(cfg)
    device = training_device(cfg.device)
    loss.to(device)  # as the trainer: the networks and the update on cfg.device, the env on the CPU
    optim = torch.optim.Adam(loss.parameters(), lr=float(cfg.optim.lr))
    steps = max(1, int(cfg.collect.frames_per_batch) // env.base_env.num_worlds)
    carried = env.reset() if ckpt is None else restore_training_state(ckpt, env, models, optim)
    times = {"policy_s": 0.0, "env_step_s": 0.0, "ppo_update_s": 0.0}
    phys = env.base_env.backend.physics if cfg.env.backend == "mujoco" else None
    raw_s = 0.0
    for it in range(iterations + 1):
        t = {k: 0.0 for k in times}
        out = []
        if phys is not None:
            recorded, stop = record_physics(phys)
        torch.set_num_threads(collect_threads)
        with torch.no_grad(), set_interaction_type(InteractionType.RANDOM):
            for _ in range(steps):
                t0 = time.perf_counter()
                carried = policy_step(models.actor, carried, device, env.device)
                t1 = time.perf_counter()
                td, carried = env.step_and_maybe_reset(carried)
                t["policy_s"] += t1 - t0
                t["env_step_s"] += time.perf_counter() - t1
                out.append(td)
        torch.set_num_threads(update_threads)
        t0 = time.perf_counter()
        ppo_update(torch.stack(out, -1).to(device), loss, optim, cfg)
        t["ppo_update_s"] = time.perf_counter() - t0
        if phys is not None:
            stop()
            if it:  # the same physics again, raw, right after the iteration that did it
                raw_s += replay_raw(phys, recorded) / iterations
        if it:  # the first iteration warms up allocations and thread pools
            times = {k: times[k] + t[k] / iterations for k in times}
    env.close()
    total = sum(times.values())
    raw = {} if phys is None else {"raw_physics_s": raw_s, "ratio_to_raw_physics": raw_s / total}
    return {"resumed_from": None if ckpt is None else str(cfg.resume),
            "resumed_iteration": None if ckpt is None else int(ckpt["counters"]["iteration"]),
            "collect_threads": collect_threads, "update_threads": update_threads, "backend": cfg.env.backend,
            "device": str(device), "num_worlds": int(cfg.env.num_worlds), "num_robots": int(cfg.env.num_robots),
            "frames_per_iteration": steps * env.base_env.num_worlds, "iterations_timed": iterations,
            "seconds_per_iteration": total, **times, **{k[:-2] + "_share": v / total for k, v in times.items()},
            "frames_per_s": steps * env.base_env.num_worlds / total, **raw}


def main(argv: list[str]) -> dict:
    opts = {a.split("=", 1)[0]: a.split("=", 1)[1] for a in argv
            if a.split("=", 1)[0] in ("iterations", "out", "threads")}
    with initialize_config_dir(config_dir=RECIPES_CONFIG, version_base="1.3"):
        cfg = compose("train", overrides=[a for a in argv if a.split("=", 1)[0] not in opts])
    cfg, ckpt = resume_config(cfg)  # with resume=: the run's settings, only RESUME_OVERRIDES from the command
    pairs = [pair.split("/") for pair in opts.get("threads", "1/1").split(",")]
    if not all(len(pair) == 2 and all(n.isdigit() and int(n) >= 1 for n in pair) for pair in pairs):
        raise ValueError(f"threads={opts['threads']!r}: expected collect/update pairs such as 1/1,1/2")
    pairs = [(int(c), int(u)) for c, u in pairs]
    before = torch.get_num_threads()
    try:
        rows = [profile(cfg, int(opts.get("iterations", 3)), *pair, ckpt=ckpt) for pair in pairs]
    finally:
        torch.set_num_threads(before)
    for row in rows:
        row["time_ratio_to_first"] = row["seconds_per_iteration"] / rows[0]["seconds_per_iteration"]
        print(f"torch threads collect {row['collect_threads']} update {row['update_threads']}: "
              f"{row['seconds_per_iteration']:.2f} s per iteration (x{row['time_ratio_to_first']:.2f}), "
              f"env {row['env_step_s']:.2f} s, update {row['ppo_update_s']:.2f} s"
              + (f", raw physics {row['raw_physics_s']:.2f} s (ratio {row['ratio_to_raw_physics']:.2f})"
                 if "raw_physics_s" in row else ""))
    result = {**rows[0], "runs": rows[1:], **provenance()}
    out = Path(opts.get("out", "runs/profile_iteration.json"))
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result, indent=1))
    return result


register()
