"""Speed of the kinematic backend through the TorchRL env, with a time breakdown.

For each robot count and batch, random valid actions are drawn once (outside the timed
loop); then ``PnPEnv(backend="kinematic").step`` (TorchRL ``EnvBase.step``) runs over
them. ``agent_steps_per_s`` = worlds x robots x env steps / s. Besides the env step, the
rows time its parts on the same state: ``backend.step`` alone (``backend_step_ms``, and
``backend_only_agent_steps_per_s`` for ``backend.step`` + ``backend.state``), the shared
task functions of ``pnp.task`` plus the output TensorDict (``task_ms``: the env's
``_observe``), and what is left (action checks, episode bookkeeping, TorchRL's
``EnvBase.step`` wrapper: ``other_ms``). Each figure is the median over ``repeats``
interleaved runs of ``steps`` steps; ``*_best`` columns are the fastest run (the least
disturbed by other processes on a shared machine).

    python recipes/bench_kinematic.py                     # prints the table
    python recipes/bench_kinematic.py --threads 1 --out results/benchmark_kinematic.json
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import time

import torch

from pnp.envs.pnp_env import PnPEnv
from pnp.task import ACTION_HIGH, ACTION_LOW


def _time_ms(fns: dict, steps: int, repeats: int) -> dict[str, list[float]]:
    """Per-step ms of each function, ``repeats`` times, interleaved so that drifts in
    machine load hit all of them alike."""
    out = {k: [] for k in fns}
    for _ in range(repeats):
        for k, fn in fns.items():
            t = time.perf_counter()
            fn()
            out[k].append((time.perf_counter() - t) / steps * 1e3)
    return out


def bench_one(robots: int, batch: int, steps: int = 20, repeats: int = 7, seed: int = 0) -> dict:
    env = PnPEnv(num_worlds=batch, num_robots=robots, backend="kinematic", seed=seed)
    g = torch.Generator().manual_seed(seed + 1)
    lo, hi = torch.tensor(ACTION_LOW), torch.tensor(ACTION_HIGH)
    actions = [lo + (hi - lo) * torch.rand(batch, robots, 8, generator=g) for _ in range(steps)]
    td = env.reset()
    backend = env.backend
    goal, dist = env._goal, env._init_goal_dist

    def env_steps():
        for a in actions:
            td.set(("agents", "action"), a)
            env.step(td)

    def backend_steps():
        for a in actions:
            backend.step(a)
            backend.state(goal, dist, a[..., 7])

    def backend_step_only():
        for a in actions:
            backend.step(a)

    def task():
        for a in actions:
            env._observe(a, a)

    env_steps()  # warm up (allocator, first-call overheads)
    t = _time_ms({"env": env_steps, "backend": backend_steps, "step": backend_step_only, "task": task}, steps, repeats)
    env.close()
    med = {k: statistics.median(v) for k, v in t.items()}
    env_ms, best_ms = med["env"], min(t["env"])
    return {
        "robots": robots, "batch": batch,
        "agent_steps_per_s": batch * robots / env_ms * 1e3, "env_steps_per_s": batch / env_ms * 1e3,
        "backend_only_agent_steps_per_s": batch * robots / med["backend"] * 1e3,
        "best_agent_steps_per_s": batch * robots / best_ms * 1e3,
        "env_step_ms": env_ms, "env_step_ms_best": best_ms, "backend_step_ms": med["step"],
        "backend_state_ms": max(med["backend"] - med["step"], 0.0), "task_ms": med["task"],
        "other_ms": max(env_ms - med["step"] - med["task"], 0.0),
        "torch_threads": torch.get_num_threads(), "steps": steps, "repeats": repeats,
    }


def bench_kinematic(batches=(1024, 4096), robots=(1, 2), steps: int = 20, repeats: int = 7,
                    threads: int | None = None) -> list[dict]:
    """Rows ``{"robots", "batch", "agent_steps_per_s", "env_steps_per_s", ...}`` (see module doc).

    ``threads`` sets ``torch.set_num_threads`` for the run (restored after); None keeps it.
    """
    old = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        return [bench_one(r, b, steps, repeats) for r in robots for b in batches]
    finally:
        torch.set_num_threads(old)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--robots", type=int, nargs="+", default=[1, 2])
    p.add_argument("--batches", type=int, nargs="+", default=[1024, 4096])
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    p.add_argument("--out", default=None, help="write the rows as JSON here")
    args = p.parse_args(argv)
    t0 = time.time()
    rows = bench_kinematic(args.batches, args.robots, args.steps, args.repeats, args.threads)
    for r in rows:
        print(f"robots={r['robots']} batch={r['batch']:5d} threads={r['torch_threads']}  "
              f"{r['agent_steps_per_s']:>10,.0f} agent-steps/s  env.step {r['env_step_ms']:.2f} ms = backend "
              f"{r['backend_step_ms']:.2f} + task {r['task_ms']:.2f} + other {r['other_ms']:.2f}  "
              f"(best run {r['best_agent_steps_per_s']:,.0f}; backend alone {r['backend_only_agent_steps_per_s']:,.0f})",
              flush=True)
    if args.out:
        os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
        with open(args.out, "w") as f:
            json.dump({"rows": rows, "wall_s": round(time.time() - t0, 1)}, f, indent=2)
        print(f"wrote {args.out}")
    return rows

