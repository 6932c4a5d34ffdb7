"""The learned low level's quality (issue 24), measured: velocity tracking over a grid of
commands, EE tracking after 0.1/0.3/1 s against the ideal low level, falls under pushes
while carrying, and how often the leg servos saturate.

    python recipes/ll_quality.py checkpoint=runs/loco out=results/ll_quality.json
    python recipes/ll_quality.py checkpoint=runs/loco pushes.episodes=16 ee.worlds=8   # quick look

Writes one JSON file with every measurement, the settings and the provenance, and a
markdown table beside it (default: ``<run>/ll_quality.json|md``).
"""
from __future__ import annotations

import time
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from pnp.sim.backend import MujocoBackend
from pnp.envs.pnp_env import PnPEnv
from pnp.sim.box import DUAL_ROBOT_BOXES, SINGLE_ROBOT_BOXES
from pnp.envs.locomotion_env import LocomotionEnv
from pnp.legs.backend import LeggedMujocoBackend
from pnp.training.checkpoint import load_checkpoint, resolve_checkpoint
from pnp.training.migration import migrate
from pnp.studies.ll_carry import dual_carry
from pnp.studies.ll_quality import command_grid, ee_tracking, locomotion_settings, push_recovery, velocity_tracking
from pnp.training.low_level import load_locomotion_policy
from pnp.training.provenance import check_clean, provenance, write_result

NEVER = 1e6  # s: a resample or push interval that never comes in a test


def _cm(x) -> str:
    return "-" if x is None else f"{100 * x:.1f}"


def table_md(r: dict) -> str:
    v, p = r["velocity_tracking"], r["pushes"]
    rows = ["| Command (vx, vy, yaw rate) | Velocity error (m/s) | Yaw-rate error (rad/s) | Falls |", "| --- | --- | --- | --- |"]
    for c in v["per_command"]:
        lin = "-" if c["lin_vel_error"] is None else f"{c['lin_vel_error']:.3f}"
        yaw = "-" if c["yaw_rate_error"] is None else f"{c['yaw_rate_error']:.3f}"
        rows.append(f"| {', '.join(f'{x:+.2f}' for x in c['command'])} | {lin} | {yaw} | {c['falls']}/{v['repeats']} |")
    rows += ["", f"Mean over commands: {v['lin_vel_error_mean'] or float('nan'):.3f} m/s, "
             f"{v['yaw_rate_error_mean'] or float('nan'):.3f} rad/s (after {v['settle_s']} s, over {v['measure_s']} s).", ""]
    delays = list(next(iter(r["ee_tracking"].values()))["ideal"]["after"])
    rows += ["| Base command | Low level | " + " | ".join(f"EE error after {d} (cm, mean / p90)" for d in delays)
             + " | Trunk height (m) | Falls |", "| --- | --- | " + " | ".join("---" for _ in delays) + " | --- | --- |"]
    for cmd, both in r["ee_tracking"].items():
        for name, e in both.items():
            cells = " | ".join(f"{_cm(e['after'][d]['mean_m'])} / {_cm(e['after'][d]['p90_m'])}" for d in delays)
            height = "-" if e["trunk_height_mean_m"] is None else f"{e['trunk_height_mean_m']:.3f}"
            rows.append(f"| {cmd} | {name} | {cells} | {height} | {e['falls']}/{e['worlds']} |")
    rows += ["", f"Pushes: {p['pushes']} kicks of {p['push_speed'][0]}-{p['push_speed'][1]} m/s every "
             f"{p['push_interval_s']:g} s over {p['episodes']} episodes of {p['seconds']:g} s with "
             f"{p['payload_kg'][0]}-{p['payload_kg'][1]} kg at the gripper: {p['falls']} falls "
             f"({100 * p['fall_rate']:.1f} % of episodes, {p['falls_per_push']:.3f} per push).", "",
             f"Saturation (share of leg joint-steps; velocity grid / pushes): torque at the limit "
             f"{100 * v['torque_saturation_rate']:.2f} % / {100 * p['torque_saturation_rate']:.2f} %, "
             f"within 0.02 rad of a range end {100 * v['joint_limit_rate']:.2f} % / {100 * p['joint_limit_rate']:.2f} %.",
             "", *carry_md(r["dual_carry"]), "", f"Leg policy `{r['checkpoint']}` (iteration {r['checkpoint_iteration']}), seed {r['seed']}."]
    return "\n".join(rows) + "\n"


def carry_md(both: dict) -> list[str]:
    rows = ["| Two robots carrying | Carried | Falls while carrying | Grasps lost | EE error (cm, mean / p90) "
            "| Lowest trunk (m, mean) | Gripper spacing drift (cm, mean / max) | Success |",
            "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for name, c in both.items():
        e, t, d = c["ee_error_m"], c["trunk_height_min_m"], c["spacing_drift_m"]
        low = "-" if t["mean"] is None else f"{t['mean']:.3f}"
        rows.append(f"| {name} | {c['carried']}/{c['episodes']} | {c['falls_while_carrying']} | "
                    f"{c['grasps_lost_while_carrying']} | {_cm(e['mean'])} / {_cm(e['p90'])} | "
                    f"{low} | "
                    f"{_cm(d['mean'])} / {_cm(d['max'])} | {c['success']}/{c['episodes']} |")
    return rows


def measure(cfg: DictConfig) -> dict:
    check_clean(cfg.out, cfg.dirty_reason)
    t0 = time.monotonic()
    path = resolve_checkpoint(cfg.checkpoint, cfg.runs_root)
    ckpt = load_checkpoint(path)
    base = migrate(ckpt["cfg"]).env.locomotion
    policy = load_locomotion_policy(str(path))
    seed, nthread = int(cfg.seed), cfg.nthread
    v, p, e = cfg.velocity, cfg.pushes, cfg.ee

    def loco_env(**changes):
        settings = locomotion_settings(base, **changes)
        return lambda n: LocomotionEnv(n, settings, seed=seed, nthread=nthread, max_episode_steps=10**9)

    grid = command_grid(base.command_low, base.command_high, int(v.grid_steps))
    velocity = velocity_tracking(loco_env(command_resample_s=NEVER, push_interval_s=NEVER), policy, grid,
                                 int(v.repeats), float(v.settle_s), float(v.measure_s))
    pushes = push_recovery(loco_env(push_interval_s=float(p.interval_s), push_speed=list(p.speed),
                                    payload_mass=list(p.payload_kg)), policy, int(p.episodes), float(p.seconds))
    box = SINGLE_ROBOT_BOXES[0]
    backends = {"ideal": lambda: MujocoBackend(int(e.worlds), 1, box, nthread=nthread),
                "learned": lambda: LeggedMujocoBackend(int(e.worlds), 1, box, policy, nthread=nthread,
                                                       servo=policy.servo)}
    tracking = {}
    for cmd in e.base_commands:
        cmd = [float(x) for x in cmd]
        both = {}
        for name, make in backends.items():
            backend = make()
            try:
                both[name] = ee_tracking(backend, int(e.switches), tuple(e.delays_s), float(e.hold_s), cmd, seed,
                                         fall_height=float(base.fall_height))
            finally:
                backend.close()
        tracking[", ".join(f"{x:+.2f}" for x in cmd)] = both
    c = cfg.carry
    mass = (float(c.box_mass_kg),) * 2
    pair = {"ideal": lambda n: PnPEnv(n, 2, "mujoco", seed=seed, nthread=nthread, paired_trials=True, box_mass=mass),
            "learned": lambda n: PnPEnv(n, 2, LeggedMujocoBackend(n, 2, DUAL_ROBOT_BOXES[0], policy, nthread=nthread,
                                                                  servo=policy.servo),
                                        seed=seed, paired_trials=True, box_mass=mass)}
    carry = {name: dual_carry(make, int(c.episodes), int(c.max_steps)) for name, make in pair.items()}
    result = {"velocity_tracking": velocity, "ee_tracking": tracking, "pushes": pushes, "dual_carry": carry,
              "settings": OmegaConf.to_container(cfg), "locomotion": OmegaConf.to_container(base),
              "checkpoint": str(path), "checkpoint_iteration": int(ckpt["counters"]["iteration"]),
              "env_steps": int(ckpt["counters"]["frames"]), "seed": seed, "wall_s": time.monotonic() - t0,
              **provenance(**({"dirty_reason": cfg.dirty_reason} if cfg.dirty_reason else {}))}
    out = Path(cfg.out) if cfg.out else path.parent / "ll_quality.json"
    return write_result(result, out, table_md(result))
