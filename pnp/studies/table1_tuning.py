"""Equal tuning for Table I (issue 68): every method tries the same configurations.

Each candidate of ``tuning.candidates`` is a set of phase overrides merged over the method's
own experiment (``as_built``: the experiment unchanged). Every method trains every candidate
through the kinematic phases with the training seed ``tuning.seed``, which is none of the
reported ``seeds`` (a reported run is then not the winner of a draw), and each run's last
kinematic policy is scored on ``tuning.eval``, whose seed must be a selection seed. The best by
success rate, then mean end stage (earlier candidates win ties), is the method's configuration
for all of its reported seeds. With one candidate there is nothing to choose and nothing runs.
"""
from __future__ import annotations

from typing import Callable

from omegaconf import DictConfig, OmegaConf, open_dict

from pnp.training.protocol import seed_role

AS_BUILT = "as_built"


def with_candidate(tcfg: DictConfig, candidates: DictConfig, name: str) -> DictConfig:
    """``tcfg`` with candidate ``name``'s overrides added to its phases' (a copy)."""
    if name not in candidates:
        raise ValueError(f"tuning candidate {name!r} is not among {list(candidates)}")
    tcfg = tcfg.copy()
    for phase, overrides in candidates[name].items():
        if phase not in tcfg.pipeline:
            raise ValueError(f"tuning.candidates.{name}: phase {phase!r} is not in the pipeline {list(tcfg.pipeline)}")
        with open_dict(tcfg.phases[phase].overrides):  # a free-form map: new keys are its purpose
            for key, value in overrides.items():
                tcfg.phases[phase].overrides[key] = value  # a dotted key stays one key, as in the YAML
    return tcfg


def run_name(method: str, candidate: str, seed: int) -> str:
    """The run folder's and the record's name (``as_built`` keeps the untuned comparison's)."""
    return f"{method}_s{seed}" if candidate == AS_BUILT else f"{method}_{candidate}_s{seed}"


def check_tuning(cfg: DictConfig) -> None:
    tuning = cfg.tuning
    if list(tuning.candidates)[:1] != [AS_BUILT]:
        raise ValueError(f"tuning.candidates must start with {AS_BUILT!r} (the experiment as built), got "
                         f"{list(tuning.candidates)}")
    if len(tuning.candidates) == 1:
        return
    if int(tuning.seed) in [int(s) for s in cfg.seeds]:
        raise ValueError(f"tuning.seed={tuning.seed} is one of the reported seeds {list(cfg.seeds)}: the chosen "
                         "configuration's reported run would be the winner of the draw")
    if seed_role(int(tuning.eval.seed)) != "selection":
        raise ValueError(f"tuning.eval.seed={tuning.eval.seed} is not a selection seed: configurations are chosen "
                         "on selection trials only (pnp.training.protocol)")


def tune(cfg: DictConfig, method: str, run_seed: Callable[[DictConfig, str, int, str], tuple]) -> dict:
    """The method's tuning: every candidate's score and the one chosen. ``run_seed(cfg, method,
    seed, candidate)`` trains (or reuses) and evaluates one run (``pnp.studies.table1.run_seed``).
    ``cfg`` passed :func:`check_tuning` (the caller checks once, before any run)."""
    names = list(cfg.tuning.candidates)
    if len(names) == 1:
        return {"configs_tried": 1, "chosen": AS_BUILT, "chosen_on": "nothing: one configuration", "candidates": {}}
    tcfg = OmegaConf.merge(cfg, {"eval_kinematic": cfg.tuning.eval, "mujoco_seeds": [],
                                 "runs_dir": f"{cfg.runs_dir}/tuning", "records_dir": f"{cfg.records_dir}/tuning"})
    tried = {}
    for name in names:
        record = run_seed(tcfg, method, int(cfg.tuning.seed), name)[0]
        score = record["eval_kinematic"]
        tried[name] = {"overrides": OmegaConf.to_container(cfg.tuning.candidates[name]),
                       "success_rate": score["success_rate"], "mean_end_stage": score["mean_end_stage"],
                       "wall_s": record["wall_s"], "frames": record["frames"]}
    chosen = max(names, key=lambda n: (tried[n]["success_rate"], tried[n]["mean_end_stage"]))  # first of ties
    return {"configs_tried": len(names), "chosen": chosen, "chosen_on": "selection seeds",
            "selection_seed": int(cfg.tuning.eval.seed), "training_seed": int(cfg.tuning.seed),
            "trials": int(cfg.tuning.eval.trials), "candidates": tried}
