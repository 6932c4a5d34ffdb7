"""Env speed against raw MuJoCo on the same work, side by side in one process.

For each robot count and batch: record a few HL steps of random actions through
``PnPEnv.step`` (TorchRL EnvBase), then time (a) the env replaying them from the same
start state and (b) raw ``mujoco.rollout`` on the same models, start states and control
trajectories (the physics the env did, without IK, observations, rewards or TorchRL).
``ratio = raw physics time / env step time`` (1.0: the env adds nothing). With
``--low-level-checkpoint`` it also times the env on the learned low level against the ideal
one on the same actions (``learned_over_ideal_speed``).

    python recipes/benchmark.py                      # writes results/benchmark_env.json
    python recipes/benchmark.py --batches 64 --steps 5 --out /tmp/b.json
    python recipes/benchmark.py --robots 1 --batches 64 256 --low-level-checkpoint runs/loco
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import time

import torch

from pnp.training.provenance import provenance

from pnp.envs.pnp_env import PnPEnv
from pnp.sim.physics import CTRL
from pnp.task import ACTION_HIGH, ACTION_LOW


def _actions(env, steps, seed):
    g = torch.Generator().manual_seed(seed)
    lo, hi = torch.tensor(ACTION_LOW), torch.tensor(ACTION_HIGH)
    shape = (steps, env.num_worlds, env.num_robots, 8)
    # Random but smooth: a random target held for the whole run, plus small noise.
    base = torch.rand(shape[1:], generator=g)
    return [lo + (hi - lo) * (base + 0.1 * torch.rand(shape[1:], generator=g)).clamp(0, 1) for _ in range(steps)]


def record_physics(phys) -> tuple[list, callable]:
    """Start recording ``phys``'s steps (start state and controls); returns the list they go
    to and a function that stops the recording."""
    recorded, real_step = [], phys.step
    phys.step = lambda ctrl: (recorded.append((phys.state.copy(), ctrl.copy())), real_step(ctrl))[1]

    def stop():
        phys.step = real_step

    return recorded, stop


def replay_raw(phys, recorded: list) -> float:
    """Seconds that raw ``mujoco.rollout`` takes for the recorded steps: the same models,
    start states and controls, without IK, observations, rewards or TorchRL."""
    t = time.perf_counter()
    for state, ctrl in recorded:
        phys._pool.rollout(phys.models, phys.datas, state, ctrl, control_spec=CTRL, skip_checks=True,
                           nstep=ctrl.shape[1], state=phys._out[0], sensordata=phys._out[1])
    return time.perf_counter() - t


def bench_env(robots: int, batch: int, steps: int, repeats: int, nthread: int | None) -> dict:
    env = PnPEnv(num_worlds=batch, num_robots=robots, seed=0, nthread=nthread)
    td0 = env.reset()
    acts = _actions(env, steps, seed=batch + robots)
    # Warm up (allocations, thread pool), then remember the start state.
    env.step(td0.clone().set(("agents", "action"), acts[0]))
    start = env.get_state()
    phys = env.backend.physics
    recorded, stop = record_physics(phys)
    _run_env(env, td0, acts)
    stop()
    env_t, raw_t = [], []
    for _ in range(repeats):  # interleaved, so drift in machine load hits both alike
        env.set_state(start)
        t = time.perf_counter()
        _run_env(env, td0, acts)
        env_t.append(time.perf_counter() - t)
        raw_t.append(replay_raw(phys, recorded))
    env.close()
    te, tr = statistics.median(env_t) / steps, statistics.median(raw_t) / steps
    return {
        "robots": robots, "batch": batch, "env_steps_per_s": batch / te, "agent_steps_per_s": batch * robots / te,
        "env_step_ms": 1e3 * te, "raw_physics_ms": 1e3 * tr, "raw_physics_steps_per_s": batch * env.backend.nsub / tr,
        "ratio": tr / te,
    }


def bench_low_level(checkpoint: str, robots: int, batch: int, steps: int, repeats: int, nthread: int | None) -> dict:
    """The PnP env on the ideal low level against the learned one (legs walked by the leg
    policy of ``checkpoint``), the same random actions, timed interleaved."""
    from pnp.sim.box import DUAL_ROBOT_BOXES, SINGLE_ROBOT_BOXES
    from pnp.legs.backend import LeggedMujocoBackend
    from pnp.training.low_level import load_locomotion_policy

    leg_policy, policy_t = load_locomotion_policy(checkpoint), []

    def timed(obs):
        t = time.perf_counter()
        out = leg_policy(obs)
        policy_t.append(time.perf_counter() - t)
        return out

    box = (SINGLE_ROBOT_BOXES if robots == 1 else DUAL_ROBOT_BOXES)[0]
    envs = {"ideal": PnPEnv(num_worlds=batch, num_robots=robots, seed=0, nthread=nthread),
            "learned": PnPEnv(num_worlds=batch, num_robots=robots, seed=0, nthread=nthread,
                              backend=LeggedMujocoBackend(batch, robots, box, timed, nthread=nthread,
                                                          servo=leg_policy.servo))}
    acts = _actions(envs["ideal"], steps, seed=batch + robots)
    times = {k: [] for k in envs}
    for _ in range(repeats):  # interleaved, so drift in machine load hits both alike
        for k, e in envs.items():
            td = e.reset()
            policy_t.clear()
            t = time.perf_counter()
            _run_env(e, td, acts)
            times[k].append(time.perf_counter() - t)
    for e in envs.values():
        e.close()
    ti, tl = (statistics.median(times[k]) / steps for k in ("ideal", "learned"))
    return {"robots": robots, "batch": batch, "ideal_env_steps_per_s": batch / ti, "learned_env_steps_per_s": batch / tl,
            "ideal_env_step_ms": 1e3 * ti, "learned_env_step_ms": 1e3 * tl,
            "leg_policy_ms_per_env_step": 1e3 * sum(policy_t) / steps, "learned_over_ideal_speed": ti / tl}


def bench_kinematic():
    from pnp.analysis.bench_kinematic import bench_kinematic as run  # needs pnp.kinematic.backend

    rows = run()
    for r in rows:
        print(f"kinematic robots={r['robots']} batch={r['batch']:5d}  {r['agent_steps_per_s']:,.0f} agent-steps/s", flush=True)
    return rows


def _run_env(env, td, acts):
    for a in acts:
        td = env.step_mdp(env.step(td.set(("agents", "action"), a)))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--robots", type=int, nargs="+", default=[1, 2])
    p.add_argument("--batches", type=int, nargs="+", default=[64, 256, 1024])
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--nthread", type=int, default=None, help="physics threads (default: all cores)")
    p.add_argument("--kinematic", action="store_true", help="also benchmark the kinematic backend "
                   "(writes benchmark_kinematic.json beside --out)")
    p.add_argument("--low-level-checkpoint", default=None, help="also time the learned low level (a task=locomotion "
                   "run) against the ideal one; writes benchmark_low_level.json beside --out")
    p.add_argument("--out", default="results/benchmark_env.json")
    args = p.parse_args(argv)
    t0 = time.time()
    rows = []
    for robots in args.robots:
        for batch in args.batches:
            row = bench_env(robots, batch, args.steps, args.repeats, args.nthread)
            rows.append(row)
            print(f"robots={robots} batch={batch:5d}  env {row['env_steps_per_s']:8.0f} steps/s  "
                  f"({row['env_step_ms']:.1f} ms)  raw physics {row['raw_physics_ms']:.1f} ms  ratio {row['ratio']:.2f}", flush=True)
    out = {"rows": rows, **provenance(seed=0, wall_s=round(time.time() - t0, 1), torch_threads=torch.get_num_threads(),
                                      steps_per_measure=args.steps, repeats=args.repeats)}
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(out, f, indent=2)
    print(f"wrote {args.out}")
    if args.low_level_checkpoint:
        t0 = time.time()
        lrows = []
        for robots in args.robots:
            for batch in args.batches:
                r = bench_low_level(args.low_level_checkpoint, robots, batch, args.steps, args.repeats, args.nthread)
                lrows.append(r)
                print(f"robots={robots} batch={batch:5d}  ideal {r['ideal_env_steps_per_s']:8.0f} steps/s  learned "
                      f"{r['learned_env_steps_per_s']:8.0f} steps/s (leg policy {r['leg_policy_ms_per_env_step']:.1f} ms "
                      f"of {r['learned_env_step_ms']:.1f})  learned/ideal speed {r['learned_over_ideal_speed']:.2f}", flush=True)
        lout = {"rows": lrows, "low_level_checkpoint": args.low_level_checkpoint,
                **provenance(seed=0, wall_s=round(time.time() - t0, 1), torch_threads=torch.get_num_threads(),
                             steps_per_measure=args.steps, repeats=args.repeats)}
        lpath = os.path.join(os.path.dirname(args.out) or ".", "benchmark_low_level.json")
        with open(lpath, "w") as f:
            json.dump(lout, f, indent=2)
        print(f"wrote {lpath}")
    if args.kinematic:
        t0 = time.time()
        krows = bench_kinematic()
        kout = {"rows": krows, **provenance(seed=0, wall_s=round(time.time() - t0, 1), torch_threads=torch.get_num_threads())}
        kpath = os.path.join(os.path.dirname(args.out) or ".", "benchmark_kinematic.json")
        with open(kpath, "w") as f:
            json.dump(kout, f, indent=2)
        print(f"wrote {kpath}")
    return out
