"""Seeds and sweeps on a Ray cluster, through Ray Tune: each run is the ``recipes/train.py``
command a user would type, in its own folder under ``out_root``, with the CPUs it may use
declared to Ray and given to it (``threads.update``, ``env.nthread``). Rerunning the same
multirun resumes every folder (a finished run returns at once): Tune's own state is not
needed to carry on after a stop.

    python recipes/ray_runs.py experiment=single_pnp_pipeline 'seeds=[0,1,2]' cpus_per_run=2 out_root=runs/seeds
    python recipes/ray_runs.py experiment=single_pnp_kinematic 'grid={optim.lr: [1e-4, 3e-4]}' address=auto
"""
from __future__ import annotations

import itertools
import json
import os
import re
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional

from omegaconf import DictConfig, OmegaConf

ROOT = Path(__file__).resolve().parents[2]
TRAIN = ROOT / "recipes" / "train.py"


@dataclass
class RayRunsConfig:
    experiment: Optional[str] = None  # experiment=<name> of every run (None: the schema's defaults)
    overrides: List[str] = field(default_factory=list)  # more train.py overrides for every run
    seeds: List[int] = field(default_factory=lambda: [0])
    grid: Dict[str, List[Any]] = field(default_factory=dict)  # override key -> values; runs = seeds x grid
    cpus_per_run: int = 2
    max_concurrent: Optional[int] = None  # None: as many as the cluster's CPUs allow
    address: Optional[str] = None  # a running cluster ("auto", "ray://host:10001"); None: a local one
    out_root: str = "runs/ray"


def ray_runs_config(overrides: list[str]) -> DictConfig:
    return OmegaConf.merge(OmegaConf.structured(RayRunsConfig), OmegaConf.from_dotlist(list(overrides)))


def run_points(cfg: DictConfig) -> list[dict]:
    """Every run's own overrides (a grid point and a seed), with its folder name."""
    keys = sorted(cfg.grid)
    points = []
    for values in itertools.product(*(list(cfg.grid[k]) for k in keys)):
        for seed in cfg.seeds:
            own = {**dict(zip(keys, values)), "seed": int(seed)}
            name = "-".join(f"{k}_{v}" for k, v in own.items())  # no '=' or ',': hydra reads them in out_dir
            points.append({"overrides": own, "name": re.sub(r"[^A-Za-z0-9_.-]", "_", name)})
    return points


def command(cfg: DictConfig, point: dict) -> list[str]:
    """The run's ``recipes/train.py`` command line, its threads set to its CPUs."""
    cpus = int(cfg.cpus_per_run)
    args = ([f"experiment={cfg.experiment}"] if cfg.experiment else []) + list(cfg.overrides)
    args += [f"{k}={v}" for k, v in point["overrides"].items()]
    args += [f"out_dir={Path(cfg.out_root).resolve() / point['name']}", f"threads.update={cpus}",
             f"env.nthread={cpus}", "logger.backend=csv", "progress=false"]
    return [sys.executable, str(TRAIN), *args]


def last_metrics(folder: Path) -> dict:
    """The run's last metrics row (a pipeline: its last phase's)."""
    rows = sorted(folder.rglob("metrics.jsonl"), key=lambda p: p.stat().st_mtime)
    if not rows:
        return {}
    lines = rows[-1].read_text().splitlines()
    row = json.loads(lines[-1]) if lines else {}
    return {k: v for k, v in row.items() if isinstance(v, (int, float))}


def _trainable(config: dict) -> None:
    from ray import tune

    folder = Path(config["out_dir"])
    folder.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "WANDB_MODE": os.environ.get("WANDB_MODE", "offline"), "OMP_NUM_THREADS": str(config["cpus"])}
    with open(folder / "ray_run.log", "a") as log:
        code = subprocess.run(config["command"], cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT).returncode
    if code != 0:
        raise RuntimeError(f"{' '.join(config['command'])} exited {code}; see {folder / 'ray_run.log'}")
    tune.report({"exit_code": code, **last_metrics(folder)})


def launch(cfg: DictConfig) -> list[dict]:
    """Runs every point on the cluster; returns per run its folder, command and last metrics."""
    import ray
    from ray import tune

    points = run_points(cfg)
    if not ray.is_initialized():
        ray.init(address=cfg.address, include_dashboard=False, log_to_driver=False,
                 **({"num_cpus": os.cpu_count()} if cfg.address is None else {}))
    out_root = Path(cfg.out_root).resolve()
    space = {"point": tune.grid_search([
        {"command": command(cfg, p), "out_dir": str(out_root / p["name"]), "cpus": int(cfg.cpus_per_run),
         "name": p["name"]} for p in points])}
    tuner = tune.Tuner(
        tune.with_resources(lambda c: _trainable(c["point"]), {"cpu": int(cfg.cpus_per_run)}),
        param_space=space,
        tune_config=tune.TuneConfig(max_concurrent_trials=cfg.max_concurrent),
        run_config=tune.RunConfig(name="ray_runs", storage_path=str(out_root / "_tune"), verbose=0),
    )
    results = tuner.fit()
    out = []
    for r in results:
        point = r.config["point"]
        out.append({"name": point["name"], "out_dir": point["out_dir"], "command": point["command"][1:],
                    "error": None if r.error is None else str(r.error), "metrics": r.metrics or {}})
    return sorted(out, key=lambda x: x["name"])
