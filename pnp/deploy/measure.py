"""The deployment's measurements (issue 65): each a set of deployed trial sets on the
evaluation layouts, compared where it says with the same trials in process.

- ``fault_free``: the deployed student against its in-process evaluation (paired trials),
  with the control loop's latency and the exported student's inference time.
- ``grid``: success and completion time against link delay x message loss.
- ``dropouts``: mocap dropouts of fixed lengths, the deployed student against its teacher
  in process under the same dropout process on its box fields and the same Gaussian noise
  (the teacher reads the simulator's stage: it cannot run over the wire). The student's own
  noise-model dropouts are off there, so the mocap's are the only ones. One difference
  stays: the teacher's held box fields are in its base frame as they were, while a robot
  re-projects the stale world-frame pose as it moves.

A fault on a message acts on all W worlds it carries, so the W trials of a batch share it:
intervals over trials are narrower than they should be under loss or reordering.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf

from pnp.deploy.config import deploy_config
from pnp.deploy.run import run
from pnp.task import HL_DT

DELAYS_S = (0.0, 0.05, 0.1, 0.2, 0.5)
LOSSES = (0.0, 0.05, 0.2)
DROPOUTS_S = (0.5, 1.0, 2.0)
# Dropouts start at 0.2 Hz per world: one every 5 s of seen markers, a few per episode.
DROPOUT_RATE_HZ = 0.2
_ROW_KEYS = ("trials", "success_rate", "completion_time_mean_s", "completion_time_std_s", "failure_causes", "carry")


def _row(result: dict, **settings) -> dict:
    s = result["summary"]
    return {**settings, **{k: s[k] for k in _ROW_KEYS if k in s}, "world": result["world"],
            "tick_period": result["tick_period"], "clients": result["clients"], "links": result["coordinator"]["links"],
            "wall_s": result["wall_s"]}


def deployed(base: DictConfig, workdir: Path, name: str, **overrides) -> dict:
    cfg = deploy_config([f"{k}={v}" for k, v in overrides.items()], base)
    return run(cfg, workdir / name)


def in_process_student(base: DictConfig) -> list[dict]:
    """The same student on the same trials in one process (``recipes/evaluate_student.py``'s student run)."""
    from pnp.deploy.student_io import load_student
    from pnp.training.protocol import resolve_seed
    from pnp.training.rollout import run_trials

    from pnp.deploy.carry import CarryStrain

    worlds = min(int(base.worlds), int(base.trials))
    s = load_student(base.checkpoint, num_worlds=worlds, seed=resolve_seed(base.seed), backend=base.backend,
                     low_level=base.low_level)
    hook = CarryStrain(worlds) if int(s.cfg.env.num_robots) == 2 else None  # the pull's reference
    records = run_trials(s.env, s.actor, int(base.trials), bool(base.progress), hook=hook)
    s.env.close()
    return records


def inference_time(onnx_path: Path) -> dict:
    """An exported student per call under onnxruntime, one robot and one thread."""
    from pnp.deploy.export import OnnxStudent, time_inference

    onnx = OnnxStudent(onnx_path, 1)
    obs, first = np.zeros((1, onnx.n_obs), np.float32), np.zeros((1, 1), np.float32)
    return {"onnxruntime_one_robot": time_inference(lambda: onnx.step(obs, first), 500)}


def fault_free(base: DictConfig, workdir: Path) -> dict:
    from pnp.training.paired import paired_comparison
    from pnp.training.rollout import summarise

    from pnp.deploy.carry import carry_summary

    result = deployed(base, workdir, "fault_free")
    reference = in_process_student(base)
    in_process = summarise(reference) | ({"carry": carry_summary(reference)} if "carry" in result["summary"] else {})
    return {"deployed": _row(result), "in_process": in_process, "tick_period": result["tick_period"],
            "paired": paired_comparison(result["records"], reference), "latency": result["latency"],
            "inference": inference_time(workdir / "fault_free" / "student.onnx"),  # the file the run used
            "trial_records": {"deployed": result["records"], "in_process": reference}}


def grid(base: DictConfig, workdir: Path, delays=DELAYS_S, losses=LOSSES) -> list[dict]:
    rows = []
    for delay in delays:
        for loss in losses:
            name = f"d{int(1000 * delay)}_l{int(100 * loss)}"
            result = deployed(base, workdir, name, **{"faults.link.delay_s": delay, "faults.link.loss": loss})
            rows.append(_row(result, delay_s=delay, loss=loss))
            print(f"delay {delay:.2f} s, loss {loss:.2f}: success {100 * rows[-1]['success_rate']:.1f} %", flush=True)
    return rows


def teacher_with_dropouts(base: DictConfig, teacher: str, length_s: float) -> dict:
    """The student's teacher in process, its box fields frozen by the same dropout process."""
    from pnp.distill.student import add_observation_noise
    from pnp.training.protocol import resolve_seed
    from pnp.training.rollout import load_policy, run_trials, summarise

    seed = resolve_seed(base.seed)
    pol = load_policy(teacher, min(int(base.worlds), int(base.trials)), seed, backend=base.backend,
                      low_level=base.low_level)
    add_observation_noise(pol.env, seed, dropout_p=DROPOUT_RATE_HZ * HL_DT, dropout_s=(length_s, length_s))
    records = run_trials(pol.env, pol.actor, int(base.trials), bool(base.progress))
    pol.env.close()
    return summarise(records)


def dropouts(base: DictConfig, workdir: Path, teacher: str, lengths=DROPOUTS_S) -> list[dict]:
    rows = []
    for length in lengths:
        mocap = {"faults.mocap.rate_hz": DROPOUT_RATE_HZ, "faults.mocap.min_s": length, "faults.mocap.max_s": length,
                 "sensor_dropouts": False}
        student = deployed(base, workdir, f"dropout_{length}", **mocap)
        rows.append({"dropout_s": length, "rate_hz": DROPOUT_RATE_HZ, "student_deployed": _row(student),
                     "teacher_in_process": {k: v for k, v in teacher_with_dropouts(base, teacher, length).items()
                                            if k in _ROW_KEYS}})
    return rows


def base_config(checkpoint: str, trials: int, overrides: list[str]) -> DictConfig:
    cfg = deploy_config([f"checkpoint={checkpoint}", f"trials={trials}", "out=null", *overrides])
    return OmegaConf.merge(cfg, {"progress": False})
