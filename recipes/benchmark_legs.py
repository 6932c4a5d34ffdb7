"""Physics speed of the planar robot against the floating base on actuated legs, side by side.

Both scenes are the arena of ``pnp.sim.scene`` with one robot and the smallest single-robot box
resting 1.2 m in front of it: the planar one is ``build_scene`` itself, the legged one the
same composition with ``Quadruped(legs="actuated")``. Each model first holds its pose for
1 s (arm at its default, fingers open), then ``mujoco.rollout`` runs ``--steps`` physics
steps on one thread from that state, ``--repeats`` times, the models interleaved so that
load from other processes hits both alike. Two workloads: ``stand`` (controls held) and
``jitter`` (new random targets at 50 Hz: leg offsets within +-0.1 rad about the stand,
planar base velocities within +-0.5 m/s and +-0.5 rad/s; at +-0.2 rad the legged robot
shuffles off and topples within ~10 s, then sinks, since only its feet touch the floor:
``*_trunk_height_end`` shows that it stayed up). ``ratio = planar / legged`` steps/s
(median over repeats; ``*_best`` is the fastest repeat).

    python recipes/benchmark_legs.py                        # writes runs/benchmark_legs.json
    python recipes/benchmark_legs.py --steps 1000 --repeats 3 --out /tmp/b.json
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time

import mujoco
import numpy as np
from mujoco import rollout

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from pnp.training.provenance import provenance  # noqa: E402

from pnp.legs.arm_gravity import ArmGravity  # noqa: E402
from pnp.sim.box import SINGLE_ROBOT_BOXES, HandleBox  # noqa: E402
from pnp.sim.robot import ARM_COMPENSATED, ARM_DEFAULT, ARM_JOINTS, FINGER_STROKE, LEG_JOINTS, Quadruped  # noqa: E402
from pnp.sim.scene import PnPArena, build_scene  # noqa: E402

BOX = SINGLE_ROBOT_BOXES[0]
SETTLE_S = 1.0
TARGET_PERIOD = 4  # physics steps per random target (50 Hz at 200 Hz physics)


def planar_model() -> mujoco.MjModel:
    return build_scene(1, BOX)[1]


def legged_model() -> mujoco.MjModel:
    arena = PnPArena()
    robot = Quadruped(name="robot0", legs="actuated")
    robot.create_root_joints(arena.attach(robot))
    arena.attach(HandleBox(asset=BOX, name="box")).add("freejoint")
    root = arena.mjcf_model
    return mujoco.MjModel.from_xml_string(root.to_xml_string(), assets=root.get_assets())


def _start(model: mujoco.MjModel) -> tuple[mujoco.MjData, np.ndarray]:
    """Data in the held pose after SETTLE_S, and the constant controls that hold it."""
    data = mujoco.MjData(model)
    ctrl = np.zeros(model.nu)
    for name, q in zip(ARM_JOINTS, ARM_DEFAULT):
        data.qpos[model.jnt_qposadr[model.joint(f"robot0/{name}").id]] = q
        ctrl[model.actuator(f"robot0/{name}").id] = q
    for name in ("finger_l", "finger_r"):
        ctrl[model.actuator(f"robot0/{name}").id] = FINGER_STROKE
    box = model.jnt_qposadr[[j for j in range(model.njnt) if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE][-1]]
    data.qpos[box : box + 3] = (1.2, 0.0, BOX.size[2] / 2)
    if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, "robot0/arm_j1_ff") >= 0:  # legged: the arm's feed-forward
        ff = ArmGravity(model, "robot0/", 0, ARM_COMPENSATED, ARM_JOINTS).torques(data.qpos[None])[0]
        ctrl[[model.actuator(f"robot0/{n}_ff").id for n in ARM_JOINTS]] = ff
    data.ctrl[:] = ctrl
    for _ in range(round(SETTLE_S / model.opt.timestep)):
        mujoco.mj_step(model, data)
    return data, ctrl


def _controls(model: mujoco.MjModel, ctrl: np.ndarray, steps: int, workload: str, seed: int) -> np.ndarray:
    out = np.tile(ctrl, (steps, 1))
    if workload == "jitter":
        rng = np.random.default_rng(seed)
        legged = model.nu > 0 and "robot0/LF_HAA" in {model.actuator(a).name for a in range(model.nu)}
        names, scale = (LEG_JOINTS, 0.1) if legged else (("base_x", "base_y", "base_yaw"), 0.5)
        ids = [model.actuator(f"robot0/{n}").id for n in names]
        targets = rng.uniform(-scale, scale, size=(-(-steps // TARGET_PERIOD), len(ids)))
        out[:, ids] = np.repeat(targets, TARGET_PERIOD, axis=0)[:steps]
    return out


def bench(steps: int, repeats: int, seed: int) -> dict:
    models = {"planar": planar_model(), "legged": legged_model()}
    rows = {}
    for workload in ("stand", "jitter"):
        runs = {}
        for name, model in models.items():
            data, ctrl = _start(model)
            spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
            state0 = np.empty(mujoco.mj_stateSize(model, spec))
            mujoco.mj_getState(model, data, state0, spec)
            control = _controls(model, ctrl, steps, workload, seed)[None]
            out = np.empty((1, steps, state0.size))
            runs[name] = (model, data, state0[None], control, out)
        times = {name: [] for name in runs}
        for _ in range(repeats):
            for name, (model, data, state0, control, out) in runs.items():
                t = time.perf_counter()
                rollout.rollout(model, data, state0, control, state=out)
                times[name].append(time.perf_counter() - t)
        row = {}
        for name, (model, _, _, _, out) in runs.items():
            row[f"{name}_steps_per_s"] = round(steps / statistics.median(times[name]))
            row[f"{name}_steps_per_s_best"] = round(steps / min(times[name]))
            row[f"{name}_trunk_height_end"] = round(float(_trunk_height(model, out[0, -1])), 3)
        row["ratio"] = round(row["planar_steps_per_s"] / row["legged_steps_per_s"], 2)
        if row["legged_trunk_height_end"] < 0.45:
            print(f"warning: the legged robot fell during {workload!r}; its timing is not representative")
        rows[workload] = row
    sizes = {name: {"nq": m.nq, "nv": m.nv, "nu": m.nu, "ngeom": m.ngeom} for name, m in models.items()}
    return {"workloads": rows, "models": sizes}


def _trunk_height(model: mujoco.MjModel, full_state: np.ndarray) -> float:
    data = mujoco.MjData(model)
    mujoco.mj_setState(model, data, full_state, mujoco.mjtState.mjSTATE_FULLPHYSICS)
    mujoco.mj_kinematics(model, data)
    return data.xpos[model.body("robot0/base").id, 2]


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--steps", type=int, default=4000, help="physics steps per timed rollout")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="runs/benchmark_legs.json")
    args = p.parse_args(argv)
    t0 = time.time()
    result = bench(args.steps, args.repeats, args.seed)
    for workload, row in result["workloads"].items():
        print(f"{workload:6s}  planar {row['planar_steps_per_s']:7d} steps/s  legged {row['legged_steps_per_s']:7d} steps/s  "
              f"ratio {row['ratio']:.2f}  (best {row['planar_steps_per_s_best']} / {row['legged_steps_per_s_best']})")
    out = {
        **result,
        **provenance(seed=args.seed, steps=args.steps, repeats=args.repeats, threads=1, wall_s=round(time.time() - t0, 1)),
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "mujoco": mujoco.__version__,
    }
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(out, f, indent=2)
    print(f"wrote {args.out}")
    return out


if __name__ == "__main__":
    main()
